"""Speed of the visibility masks per sample on one core: `camera_mask` (6 cameras) and `lidar_mask`.

Inputs: the real Occ3D label + the real nuScenes keyframe (rig, 34,688-point LIDAR_TOP sweep in key
ego) and one synthetic keyframe (`occdata synth`, 1 scene x 1 sample at 400x225: solid buildings,
so ~10x more object voxels to test than the real label: the camera test's hard case). Numba is
limited to ONE thread (`NUMBA_NUM_THREADS=1` is set before numba loads) so the figures are per core.
Timings are the median of `--repeat` warm runs (JIT compile excluded), wall-clock and CPU time
(`time.process_time`: what the one core spent, robust to other load on a shared machine).

    ./.venv/bin/python -m benchmarks.bench_visibility [--repeat 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ["NUMBA_NUM_THREADS"] = "1"  # per-core figures: set before numba is imported

import numpy as np  # noqa: E402

from benchmarks.common import OCC3D_LABEL as LABEL  # noqa: E402
from benchmarks.common import REAL_NUSCENES as ROOT  # noqa: E402
from benchmarks.provenance import machine  # noqa: E402
from occdata.constants import GRID  # noqa: E402
from occdata.formats.occ3d import read_label  # noqa: E402
from occdata.geometry import transform_points  # noqa: E402
from occdata.nuscenes.reader import load_lidar_points, load_nuscenes  # noqa: E402
from occdata.visibility import camera_mask, lidar_mask, object_voxels  # noqa: E402
from occdata.visibility.check import rig_of_sample  # noqa: E402

__all__: list[str] = []

LOWER = np.asarray(GRID.lower, np.float64)


def _median_time(fn, repeat: int) -> tuple[float, float]:  # noqa: ANN001
    """Median wall-clock and median CPU (process) seconds of `repeat` warm calls; with one numba
    thread the CPU time is what one core spends, whatever else loads the machine."""
    fn()  # compile / warm
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.median(wall)), float(np.median(cpu))


def _case(semantics: np.ndarray, K: np.ndarray, T: np.ndarray, size: np.ndarray, origin: np.ndarray,
          points: np.ndarray, repeat: int) -> dict[str, float]:
    origins = np.broadcast_to(origin, points.shape).copy()
    ml = lidar_mask(semantics, origins, points, LOWER, GRID.voxel_size)
    w_lidar, c_lidar = _median_time(lambda: lidar_mask(semantics, origins, points, LOWER, GRID.voxel_size), repeat)
    w_cam, c_cam = _median_time(lambda: camera_mask(semantics, ml, K, T, size, LOWER, GRID.voxel_size), repeat)
    return {"lidar_mask_s": w_lidar, "camera_mask_s": w_cam, "both_s": w_lidar + w_cam,
            "lidar_mask_cpu_s": c_lidar, "camera_mask_cpu_s": c_cam, "both_cpu_s": c_lidar + c_cam,
            "lidar_points": int(len(points)), "object_voxels_tested": int((object_voxels(semantics) & (ml != 0)).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()
    out: dict[str, object] = {"machine": machine(numba_threads=1)}
    # Real: the label's semantics with the real keyframe's rig and LiDAR sweep.
    sem = read_label(LABEL)["semantics"]
    K, T, size = rig_of_sample(ROOT, None, None)
    s = load_nuscenes(ROOT).samples[0]
    pts = transform_points(s.lidar.T_ego_from_lidar, load_lidar_points(s.lidar.path)[:, :3].astype(np.float64))
    out["real"] = _case(sem, K, T, size, s.lidar.T_ego_from_lidar[:3, 3], pts, args.repeat)
    # Synthetic: one keyframe of a generated world (its own rig and sweep).
    from occdata.geometry import invert_rigid
    from occdata.synth import SynthConfig, synthesize

    with tempfile.TemporaryDirectory() as tmp:
        root = synthesize(SynthConfig(out=Path(tmp) / "w", scenes=1, samples=1, seed=3, width=400, height=225,
                                      progress=False))
        s = load_nuscenes(root, version="v1.0-mini").samples[0]
        with np.load(root / "gts" / s.scene_name / s.token / "labels.npz") as z:
            sem = z["semantics"]
        K = np.stack([c.K for c in s.cameras])
        T = np.stack([invert_rigid(s.T_keyego_from_cam(i)) for i in range(len(s.cameras))])
        size = np.array([[c.width, c.height] for c in s.cameras])
        pts = transform_points(s.lidar.T_ego_from_lidar, load_lidar_points(s.lidar.path)[:, :3].astype(np.float64))
        out["synthetic"] = _case(sem, K, T, size, s.lidar.T_ego_from_lidar[:3, 3], pts, args.repeat)
    if args.json:
        print(json.dumps(out))
    else:
        for k in ("real", "synthetic"):
            r = out[k]
            print(f"{k:9s}: lidar_mask {r['lidar_mask_s'] * 1e3:.1f} ms ({r['lidar_points']} rays), camera_mask "
                  f"{r['camera_mask_s'] * 1e3:.1f} ms ({r['object_voxels_tested']} object voxels), "
                  f"both {r['both_s'] * 1e3:.1f} ms wall / {r['both_cpu_s'] * 1e3:.1f} ms CPU per sample, 1 thread")


if __name__ == "__main__":
    main()
