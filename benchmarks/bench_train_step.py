"""Seconds per optimizer step of `fastocc train` on the CPU, broken down by stage, optionally side by side
with another commit.

    # this checkout, the three configurations, real batches from a store (augmented, camera-masked losses)
    python -m benchmarks.bench_train_step --store data.zarr --json out.json
    # ... and commit 875e344 in a temporary git worktree, interleaved round by round: prints the ratio
    python -m benchmarks.bench_train_step --store data.zarr --ref 875e344 --rounds 3 --json out.json

One step = next batch (data wait) + forward (backbone+neck / view transform / 3D head incl. BEV head) +
all seven losses + backward + gradient clipping + AdamW, as the trainer does it. Each (checkout,
configuration) runs in a fresh process with the checkout first on PYTHONPATH, so both use their own
`fastocc`; rounds alternate the checkouts so that a change in machine load hits both. Per-term loss
times are the forward of each term alone (informational: the step computes them together).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["CONFIGS", "worker"]

REPO = Path(__file__).resolve().parents[1]
CONFIGS = {  # name -> (preset, input_hw, batch)
    "nano96": ("nano", (96, 256), 1),
    "nano128": ("nano", (128, 352), 1),
    "tiny256": ("tiny", (256, 704), 1),
}
TERMS = ("focal", "sem_scal", "geo_scal", "dice", "lovasz", "depth", "bev")


def _loader(store: str, hw: tuple[int, int], batch: int):
    from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader

    sample = SampleConfig(image=ImageAugConfig(height=hw[0], width=hw[1], train=True), bev=BevAugConfig(train=True))
    cfg = LoaderConfig(store=store, batch_size=batch, sample=sample, splits=("train",), seed=0)
    return make_loader(cfg, num_workers=1)


def _loss_fn():
    """The trainer's loss call of this checkout: 875e344 selected the masked voxels in the loop."""
    import dataclasses

    from fastocc.losses import occupancy_loss
    from fastocc.train import loop

    keep = getattr(loop, "_keep_masked", None)
    if keep is None:
        return occupancy_loss

    def old(logits, targets, cfg, depth, bev):
        logits, targets = keep(logits, targets)
        return occupancy_loss(logits, targets, dataclasses.replace(cfg, use_camera_mask=False), depth, bev)

    return old


def worker(config: str, store: str, steps: int, warmup: int, threads: int) -> dict:
    """Measure one configuration in this process; returns per-step stage times (s) and peak RSS."""
    import torch

    import fastocc
    from fastocc.losses import LossConfig, LossTargets, occupancy_loss
    from fastocc.model import FastOcc
    from fastocc.model.config import preset
    from fastocc.train.loop import depth_onehot

    torch.set_num_threads(threads)
    name, hw, batch = CONFIGS[config]
    cfg = preset(name, input_hw=hw)
    torch.manual_seed(0)
    model = FastOcc(cfg).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    loss_cfg = LossConfig(use_camera_mask=True)  # all seven terms on, weights 1
    loss_fn = _loss_fn()
    it = iter(_loader(store, hw, batch))
    rows = []
    cpu = []
    for k in range(warmup + steps):
        c0 = time.process_time()
        t = [time.perf_counter()]
        b = next(it)
        t.append(time.perf_counter())
        x = b.inputs()
        feat = model.image_stage(x.images)
        t.append(time.perf_counter())
        depth, bev = model.view_stage(feat, x)
        t.append(time.perf_counter())
        logits, bev_logits = model.head_stage(feat, bev, x)
        t.append(time.perf_counter())
        targets = LossTargets(voxel_labels=b.semantics, mask_camera=b.mask_camera,
                              depth_onehot=depth_onehot(b.depth_target, cfg.depth_bins), bev_multihot=b.bev_target)
        total, _ = loss_fn(logits.float(), targets, loss_cfg, depth, bev_logits)
        t.append(time.perf_counter())
        total.backward()
        t.append(time.perf_counter())
        torch.nn.utils.clip_grad_norm_(model.parameters(), 35.0)
        opt.step()
        opt.zero_grad(set_to_none=True)
        t.append(time.perf_counter())
        if k >= warmup:
            cpu.append(time.process_time() - c0)
            parts = ("data_wait", "backbone", "view_transform", "head_3d", "losses", "backward", "optimizer")
            rows.append({p: t[i + 1] - t[i] for i, p in enumerate(parts)})
    terms = {}
    with torch.no_grad():
        for term in TERMS:  # each term's forward alone, on the last batch's outputs
            one = LossConfig(use_camera_mask=True, **{k: float(k == term) for k in TERMS})
            t0 = time.perf_counter()
            for _ in range(2):
                occupancy_loss(logits.float(), targets, one, depth, bev_logits)
            terms[term] = (time.perf_counter() - t0) / 2
    med = {p: statistics.median(r[p] for r in rows) for p in rows[0]}
    step = [sum(r.values()) for r in rows]
    return {"config": config, "fastocc": str(Path(fastocc.__file__).parents[1]), "threads": threads,
            "steps": [round(s, 4) for s in step], "step_median_s": statistics.median(step),
            "cpu_steps": [round(s, 4) for s in cpu], "cpu_median_s": statistics.median(cpu),
            "samples_per_s": batch / statistics.median(step), "stages_median_s": med, "loss_terms_forward_s": terms,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _run_worker(checkout: Path, config: str, args: argparse.Namespace) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{checkout}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", config, "--store", str(args.store),
           "--steps", str(args.steps), "--warmup", str(args.warmup), "--threads", str(args.threads)]
    out = subprocess.run(cmd, env=env, cwd=checkout, capture_output=True, text=True, check=False)
    if out.returncode:
        raise SystemExit(f"worker {config} in {checkout} failed:\n{out.stderr[-3000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if Path(res["fastocc"]).resolve() != checkout.resolve():
        raise SystemExit(f"worker imported fastocc from {res['fastocc']}, not {checkout}")
    return res


def _ref_checkout(ref: str, tmp: Path) -> Path:
    if Path(ref).is_dir():
        return Path(ref).resolve()
    path = tmp / f"ref-{ref}"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(path), ref], check=True,
                   capture_output=True)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True, type=lambda s: str(Path(s).resolve()) if "://" not in s else s,
                    help="a built store with a labelled train split")
    ap.add_argument("--configs", default=",".join(CONFIGS), help=f"comma-separated, from {list(CONFIGS)}")
    ap.add_argument("--ref", help="another commit (a temporary git worktree) or checkout folder to compare")
    ap.add_argument("--rounds", type=int, default=1, help="alternating rounds (ref, this) per configuration")
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.store, args.steps, args.warmup, args.threads)))
        return
    # Imported here, not at the top: the workers run this file inside the other checkout, whose
    # benchmarks/ may predate the package.
    from benchmarks.common import write_json
    from benchmarks.provenance import machine

    record = machine()
    with tempfile.TemporaryDirectory() as tmp:
        checkouts = {"this": REPO}
        if args.ref:
            checkouts = {"ref": _ref_checkout(args.ref, Path(tmp)), **checkouts}
        try:
            results = _measure(checkouts, args)
        finally:
            if args.ref and not Path(args.ref).is_dir():
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force",
                                str(checkouts["ref"])], check=False, capture_output=True)
    summary = {"machine": record, "ref": args.ref, "results": results}
    if args.json:
        write_json(summary, args.json, indent=1)


def _measure(checkouts: dict[str, Path], args: argparse.Namespace) -> dict:
    results: dict[str, dict] = {}
    for config in args.configs.split(","):
        runs: dict[str, list[dict]] = {k: [] for k in checkouts}
        for _ in range(args.rounds):
            for key, path in checkouts.items():
                runs[key].append(_run_worker(path, config, args))
        entry = {}
        for key, rs in runs.items():
            steps = [s for r in rs for s in r["steps"]]
            stages = {p: statistics.median(r["stages_median_s"][p] for r in rs) for p in rs[0]["stages_median_s"]}
            terms = {p: statistics.median(r["loss_terms_forward_s"][p] for r in rs) for p in TERMS}
            cpu = [s for r in rs for s in r["cpu_steps"]]
            entry[key] = {"step_median_s": statistics.median(steps), "steps": steps, "stages_median_s": stages,
                          "cpu_median_s": statistics.median(cpu), "cpu_steps": cpu,
                          "loss_terms_forward_s": terms, "peak_rss_mb": max(r["peak_rss_mb"] for r in rs)}
        if "ref" in entry:
            entry["speedup"] = entry["ref"]["step_median_s"] / entry["this"]["step_median_s"]
            entry["cpu_speedup"] = entry["ref"]["cpu_median_s"] / entry["this"]["cpu_median_s"]
        results[config] = entry
        _print(config, entry)
    return results


def _print(config: str, entry: dict) -> None:
    keys = [k for k in ("ref", "this") if k in entry]
    print(f"\n{config}: seconds per step (median)")
    stages = list(entry[keys[0]]["stages_median_s"])
    print(f"  {'stage':<16}" + "".join(f"{k:>10}" for k in keys))
    for p in stages:
        print(f"  {p:<16}" + "".join(f"{entry[k]['stages_median_s'][p]:>10.3f}" for k in keys))
    for t in TERMS:
        print(f"  {'  loss ' + t:<16}" + "".join(f"{entry[k]['loss_terms_forward_s'][t]:>10.3f}" for k in keys))
    print(f"  {'step':<16}" + "".join(f"{entry[k]['step_median_s']:>10.3f}" for k in keys))
    print(f"  {'step CPU-s':<16}" + "".join(f"{entry[k]['cpu_median_s']:>10.3f}" for k in keys))
    print(f"  {'peak RSS (MB)':<16}" + "".join(f"{entry[k]['peak_rss_mb']:>10.0f}" for k in keys))
    if "speedup" in entry:
        print(f"  samples/s ratio this / ref: {entry['speedup']:.2f}x wall, {entry['cpu_speedup']:.2f}x CPU time")


if __name__ == "__main__":
    main()
