"""Per-sample costs of the data stages for docs/nuscenes.md, measured through the CLI as a user runs it.

    python -m benchmarks.walkthrough --json docs/results/walkthrough.json          # ~3-5 min on 2 cores

On trees replaying the real nuScenes keyframe (tests/replicated_tree.py: the real 1600 x 900 JPEGs, LiDAR
sweep, calibration and Occ3D label, linked, with shifted poses; 30 keyframes per scene, the last scene
val) of each `--sizes`, one command at a time, each in its own process:
- `occdata build --root TREE --gts TREE/gts --out STORE --workers 2`: samples/s, CPU seconds per sample
  (the command and every process it waited for), peak RSS of its largest process, bytes per sample of the
  store (apparent and on disk) against the input's (6 JPEGs + LiDAR + labels.npz of the keyframe);
- `occdata verify --store STORE`: samples/s, peak RSS;
- open to first batch: a fresh process opens the store and takes the first training batch of tiny's
  loader (320 x 800, train augmentation, 2 workers, as `fastocc train` does); import time apart.
And once, on the real scene-0916 (41 keyframes, boxes, no sweep files): `occdata labels --root SEQ --out
GTS`: keyframes/s, CPU seconds per keyframe, peak RSS, output bytes per keyframe.

CPU seconds and peak RSS come from `os.wait4` on the command (its own and its reaped descendants'); a
machine shared with other jobs changes wall times, much less CPU seconds: the JSON records the load.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.common import OCC3D_LABEL, REAL_NUSCENES, SHARED_DATA, emit_json
from benchmarks.provenance import REPO, finish, machine

__all__ = ["first_batch", "linear_fit", "run_command", "tree_bytes", "walkthrough"]

SAMPLES_PER_SCENE = 30
REAL_SEQ = SHARED_DATA / "nuscenes-real-seq"


def run_command(args: list[str], cwd: Path = REPO) -> dict[str, Any]:
    """Run `python -m ...args` to completion: wall seconds, CPU seconds (user + kernel, with the reaped
    descendants), peak RSS of the largest of those processes (MiB) and stdout. A failure is fatal."""
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", *args], cwd=cwd, env=env, stdout=out, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    if proc.returncode:
        raise SystemExit(f"{' '.join(args)} failed ({proc.returncode}):\n{stderr[-2000:]}")
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mib": usage.ru_maxrss / 1024,
            "stdout": stdout}


def tree_bytes(path: Path) -> dict[str, int]:
    """Apparent bytes (sum of file sizes) and bytes on disk (allocated blocks) under `path`, links not followed."""
    apparent = disk = 0
    for f in path.rglob("*"):
        st = f.lstat()
        if f.is_file() and not f.is_symlink():
            apparent += st.st_size
            disk += st.st_blocks * 512
    return {"apparent": apparent, "disk": disk}


def _input_bytes_per_sample() -> int:
    """The real keyframe's 6 JPEGs + LiDAR file + the Occ3D labels.npz (what a build reads per sample)."""
    files = [f for f in (REAL_NUSCENES / "samples").rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files) + OCC3D_LABEL.stat().st_size


def first_batch(store: str, height: int, width: int, workers: int) -> dict[str, float]:
    """In this process: seconds to import the loader, then from opening the store to the first batch (wall, and
    this process's CPU: opening and planning happen here, decoding in the workers)."""
    t0 = time.perf_counter()
    from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader

    t1, c1 = time.perf_counter(), time.process_time()
    sample = SampleConfig(image=ImageAugConfig(height=height, width=width, train=True), bev=BevAugConfig(train=True))
    loader = make_loader(LoaderConfig(store=store, batch_size=1, sample=sample, splits=("train",), seed=0),
                         num_workers=workers)
    next(iter(loader))
    return {"import_s": t1 - t0, "wall_s": time.perf_counter() - t1, "cpu_s": time.process_time() - c1}


def _one_size(n: int, tmp: Path) -> dict[str, Any]:
    from tests.replicated_tree import make_replicated_tree

    scenes = max(2, n // SAMPLES_PER_SCENE)
    n = scenes * SAMPLES_PER_SCENE
    tree = make_replicated_tree(REAL_NUSCENES, OCC3D_LABEL, tmp / f"tree{n}", scenes, SAMPLES_PER_SCENE)
    store = tmp / f"store{n}.zarr"
    build = run_command(["cli.occdata_cli", "build", "--root", str(tree), "--gts", str(tree / "gts"), "--out",
                         str(store), "--workers", "2", "--no-progress"])
    size = tree_bytes(store)
    verify = run_command(["cli.occdata_cli", "verify", "--store", str(store), "--no-progress"])
    first = run_command(["benchmarks.walkthrough", "--first-batch", str(store)])
    n_train = (scenes - 1) * SAMPLES_PER_SCENE
    return {
        "samples": n, "scenes": scenes, "train_samples": n_train,
        "build": {"samples_per_s": n / build["wall_s"], "cpu_s_per_sample": build["cpu_s"] / n,
                  "wall_s": build["wall_s"], "cpu_s": build["cpu_s"], "peak_rss_mib": build["peak_rss_mib"],
                  "workers": 2},
        "store_bytes_per_sample": {k: v / n for k, v in size.items()},
        "verify": {"samples_per_s": n / verify["wall_s"], "cpu_s_per_sample": verify["cpu_s"] / n,
                   "wall_s": verify["wall_s"], "cpu_s": verify["cpu_s"], "peak_rss_mib": verify["peak_rss_mib"]},
        "first_batch": {**json.loads(first["stdout"].strip().splitlines()[-1]), "peak_rss_mib": first["peak_rss_mib"],
                        "process_wall_s": first["wall_s"], "process_cpu_s": first["cpu_s"], "hw": [320, 800],
                        "workers": 2},
    }


def _labels(tmp: Path) -> dict[str, Any]:
    out = tmp / "gts-0916"
    run = run_command(["cli.occdata_cli", "labels", "--root", str(REAL_SEQ), "--out", str(out), "--no-progress"])
    frames = len(list(out.rglob("labels.npz")))
    size = tree_bytes(out)
    return {"tree": "real scene-0916 (boxes, keyframe LiDAR only: no sweep files)", "keyframes": frames,
            "keyframes_per_s": frames / run["wall_s"], "cpu_s_per_keyframe": run["cpu_s"] / frames,
            "wall_s": run["wall_s"], "peak_rss_mib": run["peak_rss_mib"],
            "output_bytes_per_keyframe": {k: v / frames for k, v in size.items()}}


def linear_fit(sizes: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Fixed and per-sample seconds of build, verify and open-to-first-batch from the smallest and the largest
    tree (seconds = fixed + per_sample x samples), for wall time and for CPU time: what the walkthrough
    extrapolates with (on a loaded machine the CPU fit is the one to trust)."""
    a, b = sizes[0], sizes[-1]
    dn = b["samples"] - a["samples"]
    fit = {}
    for stage in ("build", "verify", "first_batch"):
        for kind in ("wall_s", "cpu_s"):
            per = (b[stage][kind] - a[stage][kind]) / dn
            fit[f"{stage}_{kind[:-2]}"] = {"per_sample_s": per, "fixed_s": a[stage][kind] - per * a["samples"]}
    return fit


def walkthrough(sizes: list[int], labels: bool = True) -> dict[str, Any]:
    record = machine(threads="library defaults")
    with tempfile.TemporaryDirectory(prefix="walkthrough-") as tmp:
        result: dict[str, Any] = {"input_bytes_per_sample": _input_bytes_per_sample(),
                                  "sizes": [_one_size(n, Path(tmp)) for n in sizes]}
        if len(sizes) > 1:
            result["fit"] = linear_fit(result["sizes"])
        if labels:
            result["labels"] = _labels(Path(tmp))
    return {"machine": finish(record), **result}


def _print_table(result: dict[str, Any]) -> None:
    print(f"input {result['input_bytes_per_sample'] / 1e6:.2f} MB per sample", file=sys.stderr)
    for s in result["sizes"]:
        b, v, f = s["build"], s["verify"], s["first_batch"]
        print(f"{s['samples']:>6} samples: build {b['samples_per_s']:.1f}/s ({b['cpu_s_per_sample']:.3f} CPU-s, "
              f"{b['peak_rss_mib']:.0f} MiB), store {s['store_bytes_per_sample']['disk'] / 1e6:.2f} MB/sample, "
              f"verify {v['samples_per_s']:.1f}/s ({v['cpu_s_per_sample']:.3f} CPU-s, {v['peak_rss_mib']:.0f} MiB), "
              f"first batch {f['wall_s']:.1f} s ({f['cpu_s']:.1f} CPU-s; +{f['import_s']:.1f} s imports)",
              file=sys.stderr)
    for name, f in result.get("fit", {}).items():
        print(f"fit {name}: {f['fixed_s']:.1f} s + {1e3 * f['per_sample_s']:.3f} ms per sample", file=sys.stderr)
    if "labels" in result:
        lab = result["labels"]
        print(f"labels: {lab['keyframes']} keyframes, {lab['cpu_s_per_keyframe']:.2f} CPU-s each, "
              f"{lab['peak_rss_mib']:.0f} MiB", file=sys.stderr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="300,1200", help="samples per replayed tree, comma-separated")
    ap.add_argument("--no-labels", action="store_true", help="skip the occdata labels run on scene-0916")
    ap.add_argument("--json", nargs="?", const="-", help="print the result as JSON (and write it to the path)")
    ap.add_argument("--first-batch", help=argparse.SUPPRESS)  # the measuring child process
    args = ap.parse_args()
    if args.first_batch:
        print(json.dumps(first_batch(args.first_batch, 320, 800, 2)))
        return
    result = walkthrough([int(s) for s in args.sizes.split(",")], labels=not args.no_labels)
    _print_table(result)
    if args.json:
        emit_json(result, None if args.json == "-" else args.json)


if __name__ == "__main__":
    main()
