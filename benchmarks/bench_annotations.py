"""Benchmark `occdata.nuscenes.load_annotations` and `Annotations.boxes_at` on a made-up
sample_annotation table of N rows (40-box tracks, 5,000 samples; nuScenes trainval has ~1.17M rows).

    python -m benchmarks.bench_annotations [--rows 200000] [--json out.json]

Reports the load time, the growth of the process's peak RSS while loading (the JSON rows and the
records together), and the time per `boxes_at` call on an interpolated sweep.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import write_json
from benchmarks.provenance import REPO, machine
from occdata.nuscenes import load_annotations

__all__ = ["measure", "write_tables"]

N_SAMPLES, TRACK = 5000, 40


def write_tables(vdir: Path, rows: int) -> None:
    """sample, category, instance and sample_annotation tables: `rows` boxes in tracks of 40."""
    vdir.mkdir(parents=True)
    samples = [{"token": f"s{i:031d}", "timestamp": 1_000_000 + i * 500_000,
                "prev": f"s{i - 1:031d}" if i else "", "next": ""} for i in range(N_SAMPLES)]
    instances = [{"token": f"i{i:031d}", "category_token": "c" * 32} for i in range(rows // TRACK + 1)]
    anns = []
    for k in range(rows):
        j = k % TRACK
        anns.append({
            "token": f"a{k:031d}", "sample_token": f"s{(k // TRACK + j) % N_SAMPLES:031d}",
            "instance_token": f"i{k // TRACK:031d}", "translation": [100.0 + j, 200.0 - j, 1.0],
            "size": [1.9, 4.6, 1.7], "rotation": [0.9, 0.0, 0.0, 0.4358898943540674],
            "prev": f"a{k - 1:031d}" if j else "", "next": f"a{k + 1:031d}" if j < TRACK - 1 else "",
            "num_lidar_pts": 12, "num_radar_pts": 0, "visibility_token": "4", "attribute_tokens": [],
        })
    for name, table in (("sample", samples), ("category", [{"token": "c" * 32, "name": "vehicle.car"}]),
                        ("instance", instances), ("sample_annotation", anns)):
        (vdir / f"{name}.json").write_text(json.dumps(table))


def _peak_rss_kb() -> int:
    """This process's peak resident set (VmHWM, kB; Linux). Unlike ru_maxrss it is not inherited
    from the parent that forked this process."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return 0


def measure(root: Path) -> dict:
    """Load `root` in this (fresh) process: load time, peak-RSS growth, and `boxes_at` per call."""
    rss0 = _peak_rss_kb()
    t0 = time.perf_counter()
    ann = load_annotations(root, "v")
    load_s = time.perf_counter() - t0
    rss_mb = (_peak_rss_kb() - rss0) / 1024
    n_calls, t_prev, t_cur = 200, 1_000_000 + 99 * 500_000, 1_000_000 + 100 * 500_000
    t0 = time.perf_counter()
    for _ in range(n_calls):
        boxes = ann.boxes_at(f"s{100:031d}", f"s{99:031d}", t_prev, t_cur, t_prev + 250_000)
    call_ms = (time.perf_counter() - t0) / n_calls * 1e3
    return {"load_s": round(load_s, 2), "peak_rss_growth_mb": round(rss_mb), "boxes_per_sample": len(boxes),
            "boxes_at_ms": round(call_ms, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=200_000)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--measure", type=Path, help=argparse.SUPPRESS)  # internal: the child process
    args = ap.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return
    record = machine()
    with tempfile.TemporaryDirectory() as tmp:
        write_tables(Path(tmp) / "v", args.rows)
        # a fresh process, so the peak RSS is the loading's alone
        res = subprocess.run([sys.executable, "-m", "benchmarks.bench_annotations", "--measure", tmp], cwd=REPO,
                             capture_output=True, text=True, check=True)
    out = {"rows": args.rows, **json.loads(res.stdout), "machine": record}
    print(json.dumps(out))
    if args.json:
        write_json(out, args.json, indent=1)


if __name__ == "__main__":
    main()
