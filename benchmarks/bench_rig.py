"""The cost per keyframe of merging several LiDARs into the depth targets, on the REAL Lyft keyframes
(../shared/data/lyft-real: 7 cameras at 1920x1080; LIDAR_TOP ~108k points, two bumper LiDARs ~39k each).

For each LiDAR set (the reference alone, then all three), every keyframe's depth targets are computed
as `occdata build` computes them (`occdata.store.sample.depth_points`: read each LiDAR file, project it
through its own calibration and ego pose into every camera), `--repeats` times; the figure is the median
CPU time (process time, one thread) per keyframe, and the rows kept per keyframe.

    python -m benchmarks.bench_rig [--repeats 3] [--json docs/results/bench_rig_lyft.json]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from benchmarks.common import SHARED_DATA, emit_json
from benchmarks.provenance import machine
from occdata.nuscenes import load_nuscenes
from occdata.nuscenes.rig import RigChoice
from occdata.store.sample import depth_points

__all__ = ["measure"]

LYFT = SHARED_DATA / "lyft-real"
LIDAR_SETS = (("LIDAR_TOP",), ("LIDAR_TOP", "LIDAR_FRONT_LEFT", "LIDAR_FRONT_RIGHT"))


def measure(root: Path, lidars: tuple[str, ...], repeats: int) -> dict[str, float]:
    """Median CPU-ms per keyframe of the depth targets from `lidars`, and the rows and points per keyframe."""
    ds = load_nuscenes(root, rig=RigChoice(lidars=lidars))
    per_round, rows = [], 0
    for _ in range(repeats):
        t0 = time.process_time()
        rows = 0
        for s in ds.samples:
            rig = s.camera_rig()
            uvd = depth_points(s, (), rig.K, rig.image_size, 0.0)
            rows += sum(len(u) for u in uvd)
        per_round.append((time.process_time() - t0) / len(ds.samples))
    points = sum(os.stat(r.path).st_size // 20 for s in ds.samples for r in s.lidars)
    return {"cpu_ms_per_keyframe": round(1e3 * statistics.median(per_round), 2),
            "cpu_ms_per_keyframe_rounds": [round(1e3 * t, 2) for t in per_round],
            "depth_rows_per_keyframe": round(rows / len(ds.samples), 1),
            "lidar_points_per_keyframe": round(points / len(ds.samples), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=LYFT)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    prov = machine(repeats=a.repeats, numba_threads=os.environ["NUMBA_NUM_THREADS"])
    measure(a.root, LIDAR_SETS[0], 1)  # compile the projection kernels once, outside the timing
    rows = {"+".join(s): measure(a.root, s, a.repeats) for s in LIDAR_SETS}
    one, all3 = (rows["+".join(s)] for s in LIDAR_SETS)
    emit_json({"machine": prov, "keyframes": len(load_nuscenes(a.root).samples), "lidar_sets": rows,
               "ratio_cpu_3_lidars_over_1": round(all3["cpu_ms_per_keyframe"] / one["cpu_ms_per_keyframe"], 3),
               "ratio_points_3_lidars_over_1": round(all3["lidar_points_per_keyframe"]
                                                     / one["lidar_points_per_keyframe"], 3),
               "numpy": np.__version__}, a.json)


if __name__ == "__main__":
    main()
