"""Benchmark BEV-flip test-time augmentation: time factor and metric change on a split.

Runs `fastocc.infer.evaluate` on the same split without and with `--tta`, interleaved, `--repeats`
times each; the time factor is min(TTA prediction time) / min(plain prediction time), where prediction
time = loading + network (what `fastocc eval` reports as frames/s; metric time excluded). The metrics
(mIoU with the camera mask, RayIoU) are deterministic, so one value each.

Without --store a synthetic world is written and built in a temporary folder (`occdata synth`; train
and val scenes). Without --checkpoint a randomly initialised nano network is used (seed 0): its TTA
metric change says nothing about a trained model, and the output says which weights were used.

    python -m benchmarks.bench_tta [--store S] [--checkpoint C] [--split val] [--repeats 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from benchmarks.common import emit_json
from benchmarks.provenance import machine
from fastocc.checkpoint import load_model
from fastocc.infer import PredictConfig
from fastocc.infer.evaluate import EvalReport, evaluate
from fastocc.infer.score import report_metrics
from fastocc.model import FastOcc, preset

__all__ = ["make_store"]


def make_store(tmp: Path, scenes: int, samples: int, width: int, height: int) -> Path:
    from occdata.store.build import BuildConfig, build_store
    from occdata.synth import SynthConfig, synthesize

    root = synthesize(SynthConfig(out=tmp / "world", scenes=scenes, samples=samples, seed=7, width=width,
                                  height=height, progress=False))
    out = tmp / "data.zarr"
    build_store(BuildConfig(root=root, out=out, gts=root / "gts", progress=False))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", type=Path, default=None)
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--split", default="val")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--batch-size", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--synth-scenes", type=int, default=2)
    ap.add_argument("--synth-samples", type=int, default=6)
    ap.add_argument("--synth-size", default="800x450", help="WxH of the synthetic images")
    ap.add_argument("--json", type=Path, default=None, help="Also write the summary here.")
    args = ap.parse_args()
    record = machine(threads=torch.get_num_threads(), device=args.device)
    with tempfile.TemporaryDirectory() as tmp:
        store = args.store
        if store is None:
            w, h = (int(v) for v in args.synth_size.split("x"))
            store = make_store(Path(tmp), args.synth_scenes, args.synth_samples, w, h)
        if args.checkpoint is not None:
            model, ckpt = load_model(args.checkpoint, device=args.device)
            cfg, weights = ckpt.model_config, f"checkpoint {args.checkpoint} (meta {ckpt.meta})"
        else:
            torch.manual_seed(0)
            cfg = preset("nano")
            model, weights = FastOcc(cfg).to(args.device).eval(), "random-init nano (seed 0): NOT a trained model"
        runs: dict[bool, list[EvalReport]] = {False: [], True: []}
        for _ in range(args.repeats):
            for tta in (False, True):
                pc = PredictConfig(store=store, split=args.split, batch_size=args.batch_size, tta=tta,
                                   device=args.device)
                runs[tta].append(evaluate(model, cfg, pc, progress=False))
        plain = min(runs[False], key=lambda r: r.infer_seconds)
        aug = min(runs[True], key=lambda r: r.infer_seconds)
        summary = {
            "machine": record,
            "store": str(args.store) if args.store else f"synthetic {args.synth_scenes} scenes x "
                                                        f"{args.synth_samples} samples, {args.synth_size}",
            "split": args.split, "weights": weights, "model": cfg.name, "input_hw": list(cfg.input_hw),
            "repeats": args.repeats,
            "plain": report_metrics(plain), "tta": report_metrics(aug),
            "time_factor": aug.infer_seconds / plain.infer_seconds,
            "miou_change_points": 100 * (aug.miou.miou - plain.miou.miou),
            "rayiou_change_points": 100 * (aug.rayiou.rayiou - plain.rayiou.rayiou),
        }
    emit_json(summary, args.json)


if __name__ == "__main__":
    main()
