"""Benchmark the metrics: RayIoU and mIoU samples/s per core, memory over a growing split.

    taskset -c 0 python -m benchmarks.bench_metrics --json     # per-core figures (one numba thread)

- RayIoU: the real Occ3D label (shared/data/occ3d-label) as truth, a perturbed copy as prediction
  (shifted one voxel along x, 5% of occupied voxels relabelled, 3% cleared), 8 origins spread
  along x like a scene's keyframes; one numba thread.
- mIoU from files on disk: N prediction files (np.savez_compressed, as Occ3D ships labels) and
  N truth files (semantics + mask_camera) read with np.load, accumulated into one confusion matrix;
  also the cost of each part (load prediction, load truth, accumulate).
- Memory: resident set size after N and after 4N samples of each loop (streaming: it must not grow).
- `occdata eval` end to end on a synthetic store (`--store-samples`, 0 to skip): the real command's
  path (store reads, origins from poses), mIoU-only and with RayIoU.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import OCC3D_LABEL as LABEL
from benchmarks.common import emit_json
from benchmarks.provenance import finish, machine

__all__ = ["bench_eval_store", "bench_miou_files", "bench_rayiou"]


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _perturb(sem: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    pred = np.roll(sem, 1, axis=0)
    occ = np.flatnonzero(pred.ravel() != 17)
    flip = rng.choice(occ, int(0.05 * occ.size), replace=False)
    clear = rng.choice(occ, int(0.03 * occ.size), replace=False)
    flat = pred.reshape(-1)
    flat[flip] = rng.integers(0, 17, flip.size)
    flat[clear] = 17
    return pred


def bench_rayiou(sem: np.ndarray, n: int, rng: np.random.Generator) -> dict:
    from occdata.eval.metrics import RayIoUAccumulator

    origins = np.c_[np.linspace(-30, 30, 8), rng.uniform(-2, 2, 8), np.full(8, 1.84)]
    preds = [_perturb(sem, rng) for _ in range(4)]
    acc = RayIoUAccumulator()
    acc.update(sem, preds[0], origins)  # compile / load the numba cache
    rss = {}
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(4 * n):
        acc.update(sem, preds[i % 4], origins)
        if i + 1 in (n, 4 * n):
            rss[i + 1] = _rss_mb()
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    r = acc.result()
    return {"samples": 4 * n, "samples_per_s": 4 * n / dt, "samples_per_cpu_s": 4 * n / dc,
            "rays_per_sample": 8 * 14040,
            "rss_mb_after": rss, "rayiou_perturbed_pct": round(100 * r.rayiou, 2),
            "rayiou_at_pct": {f"{k:g}": round(100 * v, 2) for k, v in r.rayiou_at.items()}}


def bench_miou_files(sem: np.ndarray, mask: np.ndarray, n: int, rng: np.random.Generator, tmp: Path) -> dict:
    from occdata.eval.metrics import MIoUAccumulator

    pred_dir, gt_dir = tmp / "pred", tmp / "gt"
    pred_dir.mkdir()
    gt_dir.mkdir()
    base = [_perturb(sem, rng) for _ in range(4)]
    for i in range(4 * n):
        np.savez_compressed(pred_dir / f"{i:05d}.npz", semantics=base[i % 4])
        np.savez_compressed(gt_dir / f"{i:05d}.npz", semantics=sem, mask_camera=mask)
    pred_files = sorted(pred_dir.iterdir())
    gt_files = sorted(gt_dir.iterdir())

    acc = MIoUAccumulator()
    acc.update(sem, base[0], mask)  # compile
    rss = {}
    t_pred = t_gt = t_acc = 0.0
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(4 * n):
        a = time.process_time()  # CPU time: the shared VM's wall clock includes waiting for the core
        with np.load(pred_files[i], allow_pickle=False) as z:
            pred = z["semantics"]
        b = time.process_time()
        with np.load(gt_files[i], allow_pickle=False) as z:
            gt, m = z["semantics"], z["mask_camera"]
        c = time.process_time()
        acc.update(gt, pred, m)
        t_pred += b - a
        t_gt += c - b
        t_acc += time.process_time() - c
        if i + 1 in (n, 4 * n):
            rss[i + 1] = _rss_mb()
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    # uncompressed prediction files (np.savez), for comparison
    raw = tmp / "raw.npz"
    np.savez(raw, semantics=base[0])
    t = time.process_time()
    for _ in range(200):
        with np.load(raw, allow_pickle=False) as z:
            z["semantics"]
    t_raw = (time.process_time() - t) / 200
    return {"samples": 4 * n, "samples_per_s": 4 * n / dt, "samples_per_cpu_s": 4 * n / dc, "rss_mb_after": rss,
            "cpu_ms_per_sample": {"load_prediction_npz_compressed": 1e3 * t_pred / (4 * n),
                              "load_truth_npz_compressed (semantics+mask)": 1e3 * t_gt / (4 * n),
                              "accumulate": 1e3 * t_acc / (4 * n),
                              "load_prediction_npz_uncompressed": 1e3 * t_raw},
            "accumulate_only_samples_per_cpu_s": (4 * n) / t_acc,
            "miou_perturbed_pct": round(100 * acc.result().miou, 2)}


def bench_eval_store(samples: int, tmp: Path) -> dict:
    """`evaluate_predictions` on a synthetic store of one scene (ground truth copied as predictions)."""
    import shutil

    from occdata.eval.evaluate import EvalConfig, evaluate_predictions
    from occdata.store.build import BuildConfig, build_store
    from occdata.synth import SynthConfig, synthesize

    root = synthesize(SynthConfig(out=tmp / "world", scenes=2, samples=samples, seed=3, width=160, height=90,
                                  progress=False))
    store = tmp / "data.zarr"
    build_store(BuildConfig(root=root, out=store, gts=root / "gts", progress=False))
    pred = tmp / "eval_pred"
    from occdata.store.reader import open_store

    for scene in open_store(store).attrs["scenes"]:
        if scene["split"] == "val":
            shutil.copytree(root / "gts" / scene["name"], pred / scene["name"])
    out = {}
    for name, rayiou in (("miou_only", False), ("miou_and_rayiou", True)):
        evaluate_predictions(EvalConfig(pred=pred, store=store, split="val", rayiou=rayiou, progress=False))
        c0 = time.process_time()
        rep = evaluate_predictions(EvalConfig(pred=pred, store=store, split="val", rayiou=rayiou, progress=False))
        dc = time.process_time() - c0
        out[name] = {"samples": rep.n_samples, "samples_per_s": rep.n_samples / rep.seconds,
                     "samples_per_cpu_s": rep.n_samples / dc,
                     "miou_pct": round(100 * rep.miou.miou, 2),
                     "rayiou_pct": round(100 * rep.rayiou.rayiou, 2) if rep.rayiou else None}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="Print one JSON object.")
    ap.add_argument("--rayiou-n", type=int, default=10, help="N for RayIoU (runs 4N samples).")
    ap.add_argument("--miou-n", type=int, default=100, help="N for mIoU from files (runs 4N samples).")
    ap.add_argument("--store-samples", type=int, default=20, help="Samples per scene, end-to-end store (0: skip).")
    ap.add_argument("--threads", type=int, default=1, help="numba threads (1 = per-core figures).")
    args = ap.parse_args()

    import numba

    numba.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    with np.load(LABEL, allow_pickle=False) as z:
        sem, mask = z["semantics"], z["mask_camera"]
    res: dict = {"machine": machine(numba_threads=numba.get_num_threads())}
    res["rayiou"] = bench_rayiou(sem, args.rayiou_n, rng)
    with tempfile.TemporaryDirectory() as tmp:
        res["miou_files"] = bench_miou_files(sem, mask, args.miou_n, rng, Path(tmp))
    if args.store_samples:
        with tempfile.TemporaryDirectory() as tmp:
            res["eval_store"] = bench_eval_store(args.store_samples, Path(tmp))
    finish(res["machine"])
    if args.json:
        emit_json(res, None)
        return
    r, m = res["rayiou"], res["miou_files"]
    print(f"RayIoU: {r['samples_per_s']:.1f} samples/s ({r['samples_per_cpu_s']:.1f} per CPU-second), "
          f"{r['rays_per_sample']} rays x 2 grids, RSS MB {r['rss_mb_after']}")
    print(f"mIoU from files: {m['samples_per_s']:.1f} samples/s ({m['samples_per_cpu_s']:.1f} per CPU-second); "
          f"CPU ms/sample {m['cpu_ms_per_sample']}; RSS MB {m['rss_mb_after']}")
    if "eval_store" in res:
        print(f"occdata eval (synthetic store): {res['eval_store']}")


if __name__ == "__main__":
    main()
