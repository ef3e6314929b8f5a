"""A/B build throughput of two checkouts of this repository on the same tree, 1 worker.

Fresh builds alternate between checkout A and checkout B (A, B, A, B, ...), each in its own process
pinned to one core, so both see the same machine state; noise from other processes only adds time,
so the minimum over the rounds is the figure to compare (the median is reported too). The CPU time
of the building process is reported as well: on a shared, loaded machine it is the steadier measure
of throughput per core.

    git archive <commit> | tar -x -C /tmp/a      # the checkout before a change
    taskset -c 0 python -m benchmarks.bench_build_ab --a /tmp/a --b . --root TREE --gts TREE/gts \\
        --rounds 7 --json out.json
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import emit_json
from benchmarks.provenance import finish, machine

__all__ = ["one_build"]

# Run with cwd = the checkout: `python -c` puts the working folder first on sys.path, so the child
# imports that checkout's occdata (not the installed one).
_CHILD = """
import time
from pathlib import Path
import cv2
cv2.setNumThreads(1)
from occdata.store.build import BuildConfig, build_store
cfg = BuildConfig(root=Path({root!r}), out=Path({out!r}), gts={gts}, progress=False)
t, c = time.perf_counter(), time.process_time()
report = build_store(cfg)
print(time.perf_counter() - t, time.process_time() - c, report.n_samples, report.n_done)
"""


def one_build(repo: Path, root: Path, gts: Path | None, out: Path) -> tuple[float, float, int]:
    """(wall seconds, CPU seconds of the building process, samples) of one fresh build."""
    shutil.rmtree(out, ignore_errors=True)
    code = _CHILD.format(root=str(root), out=str(out),
                         gts=f"Path({str(gts)!r})" if gts else "None")
    res = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, check=True)
    seconds, cpu, n, done = res.stdout.split()[-4:]
    if int(done) != int(n):
        raise SystemExit(f"{repo}: only {done}/{n} samples built")
    return float(seconds), float(cpu), int(n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", type=Path, required=True, help="checkout A (e.g. before the change)")
    ap.add_argument("--b", type=Path, required=True, help="checkout B (e.g. after the change)")
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--gts", type=Path)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    record = machine()
    times: dict[str, list[float]] = {"a": [], "b": []}
    cpu: dict[str, list[float]] = {"a": [], "b": []}
    n = 0
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.rounds):
            for key in ("a", "b"):
                t, c, n = one_build(getattr(args, key), args.root, args.gts, Path(tmp) / f"{key}.zarr")
                times[key].append(t)
                cpu[key].append(c)
    summary = {
        "machine": finish(record),
        "affinity": sorted(os.sched_getaffinity(0)),
        "tree": str(args.root), "samples": n, "rounds": args.rounds,
    }
    for key in ("a", "b"):
        t = np.array(times[key])
        c = np.array(cpu[key])
        summary[key] = {"checkout": str(args.a if key == "a" else args.b), "seconds": t.tolist(),
                        "cpu_seconds": c.tolist(),
                        "best_samples_per_s": n / t.min(), "median_samples_per_s": n / float(np.median(t)),
                        # per core of CPU time actually used: less sensitive to a loaded machine
                        "best_samples_per_cpu_s": n / c.min(), "median_samples_per_cpu_s": n / float(np.median(c))}
    summary["b_over_a_time_best"] = min(times["b"]) / min(times["a"])
    summary["b_over_a_time_median"] = float(np.median(times["b"]) / np.median(times["a"]))
    summary["b_over_a_cpu_best"] = min(cpu["b"]) / min(cpu["a"])
    summary["b_over_a_cpu_median"] = float(np.median(cpu["b"]) / np.median(cpu["a"]))
    emit_json(summary, args.json)


if __name__ == "__main__":
    main()
