"""Benchmark `occdata synth`: a 2-scene x 10-sample world at 1600x900, cold (fresh numba cache,
compilation included) and warm (cache populated), plus per-stage costs.

    python -m benchmarks.bench_synth            # human-readable
    python -m benchmarks.bench_synth --json     # one JSON object

Each end-to-end run is a fresh Python process (imports + numba cache loading included).
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

from benchmarks.provenance import REPO, machine

__all__: list[str] = []

CHILD = """
import json, sys, time
t0 = time.perf_counter()
from pathlib import Path
from occdata.synth import SynthConfig, synthesize
synthesize(SynthConfig(out=Path(sys.argv[1]), scenes=int(sys.argv[2]), samples=int(sys.argv[3]), seed=0,
                       width=int(sys.argv[4]), height=int(sys.argv[5]), progress=False))
print(json.dumps({"seconds": time.perf_counter() - t0}))
"""


def _run(out: Path, cache: Path, args: argparse.Namespace) -> float:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(REPO)}
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", CHILD, str(out), str(args.scenes), str(args.samples), str(args.width),
                          str(args.height)], env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    json.loads(res.stdout.strip().splitlines()[-1])
    return wall


def _stages(args: argparse.Namespace) -> dict[str, float]:
    """Warm per-stage costs on one keyframe (median of 3)."""
    import numpy as np

    from occdata.constants import FREE_LABEL, GRID
    from occdata.geometry import invert_rigid
    from occdata.synth import pipeline as P
    from occdata.synth.labels import world_semantics
    from occdata.synth.rig import RIG, camera_K
    from occdata.synth.world import make_world
    from occdata.visibility import camera_mask, lidar_mask

    t = time.perf_counter()
    world = make_world(np.random.default_rng([0, 0]), (1000.0, 1000.0), P.BASE_TIMESTAMP_US, args.samples)
    out = {"make_world_s": time.perf_counter() - t}
    ts = P.BASE_TIMESTAMP_US + 100_000 + 1_000_000
    T_ge = P.ego_transform(world, ts)
    timings: dict[str, list[float]] = {k: [] for k in ("grid_build_s", "camera_render_s", "lidar_s", "labels_s",
                                                       "camera_mask_s")}
    for _ in range(3):
        t = time.perf_counter()
        wg = P.WorldGrid.build(world, ts)
        timings["grid_build_s"].append(time.perf_counter() - t)
        T = T_ge @ RIG["CAM_FRONT"].T_ego_from_sensor
        K = camera_K("CAM_FRONT", args.width, args.height)
        t = time.perf_counter()
        P.render_camera(world, wg, T, K, args.width, args.height)
        timings["camera_render_s"].append(time.perf_counter() - t)
        t = time.perf_counter()
        P.render_lidar(world, wg, T_ge @ RIG["LIDAR_TOP"].T_ego_from_sensor)
        timings["lidar_s"].append(time.perf_counter() - t)
        t = time.perf_counter()
        sem = world_semantics(world.ground, wg.prims, T_ge)
        timings["labels_s"].append(time.perf_counter() - t)
        T_cam_from_keyego = invert_rigid(invert_rigid(T_ge) @ T)
        observed = lidar_mask(sem, np.zeros((0, 3)), np.zeros((0, 3)), np.asarray(GRID.lower), GRID.voxel_size)
        observed[sem != FREE_LABEL] = 1  # every occupied voxel observed: the camera test's worst case
        t = time.perf_counter()
        camera_mask(sem, observed, K[None], T_cam_from_keyego[None], np.array([[args.width, args.height]]),
                    np.asarray(GRID.lower), GRID.voxel_size)
        timings["camera_mask_s"].append(time.perf_counter() - t)
    out.update({k: float(np.median(v)) for k, v in timings.items()})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()
    result: dict[str, object] = {"machine": machine(), "world": vars(args).copy()}
    result["world"].pop("json")  # type: ignore[union-attr]
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "numba-cache"
        result["cold_s"] = _run(Path(tmp) / "cold", cache, args)
        result["warm_s"] = _run(Path(tmp) / "warm", cache, args)
        n = args.scenes * args.samples
        result["images"] = 6 * n
        result["warm_per_sample_s"] = result["warm_s"] / n  # type: ignore[operator]
        result["bytes_written"] = sum(p.stat().st_size for p in (Path(tmp) / "warm").rglob("*") if p.is_file())
    result["stages_warm"] = _stages(args)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    m = result["machine"]
    print(f"machine: {m['cpu']} ({m['cores']} cores), load avg at start {m['loadavg_1min']:.2f}")
    print(f"world: {args.scenes} scenes x {args.samples} samples at {args.width}x{args.height} "
          f"({result['images']} images, {result['bytes_written'] / 1e6:.0f} MB)")
    print(f"cold (fresh numba cache): {result['cold_s']:.1f} s   warm: {result['warm_s']:.1f} s "
          f"({result['warm_per_sample_s']:.2f} s/sample)")
    for k, v in result["stages_warm"].items():  # type: ignore[union-attr]
        print(f"  {k:18s} {v * 1000:8.1f} ms")


if __name__ == "__main__":
    main()
