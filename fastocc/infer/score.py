"""Score a checkpoint on a store split and get the figures as a flat, JSON-ready dict.

For scripts that compare many checkpoints (learning curves, ablation tables, TTA on/off):
`fastocc eval` prints a table, these return numbers to cache and plot.

    from fastocc.infer.score import score_checkpoint
    s = score_checkpoint("runs/a/last.pt", "data.zarr", split="val", rayiou=True)
    s["miou"], s["rayiou"], s["opt_steps"]

Values are fractions in [0, 1] (not percent); the metric code is `fastocc.infer.evaluate` (mIoU
with the camera mask, RayIoU without), nothing is re-implemented here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from fastocc.checkpoint import load_model
from fastocc.infer.evaluate import EvalReport, MaskKind, evaluate
from fastocc.infer.predict import PredictConfig
from fastocc.model.noise import noise_hook

__all__ = ["NOISE_SEED", "report_metrics", "score_checkpoint"]

NOISE_SEED = 12345  # the noise-image ablation's evaluation noise (fixed: repeated scores agree)


def report_metrics(report: EvalReport) -> dict[str, Any]:
    """The headline figures of an `EvalReport`: miou, geo_iou, rayiou (None when not computed),
    infer_seconds (loading + network, TTA included), frames_per_s and the samples scored."""
    return {"miou": float(report.miou.miou), "geo_iou": float(report.miou.geo_iou),
            "rayiou": None if report.rayiou is None else float(report.rayiou.rayiou),
            "infer_seconds": float(report.infer_seconds), "frames_per_s": float(report.frames_per_s),
            "samples": int(report.samples)}


def score_checkpoint(
    checkpoint: str | Path,
    store: str | Path,
    split: str | None = "val",
    *,
    rayiou: bool = True,
    tta: bool = False,
    mask: MaskKind = "camera",
    noise_images: bool = False,
    workers: int = 0,
    batch_size: int = 1,
    device: str = "cpu",
    prefer_ema: bool = True,
) -> dict[str, Any]:
    """Load `checkpoint` (its own model config; EMA weights if it has them and `prefer_ema`) and score
    `split` of `store`.

    `noise_images`: the backbone sees Gaussian noise instead of the camera images (seeded with
    NOISE_SEED), for runs trained that way (the image ablation). Returns `report_metrics` plus
    checkpoint (file name), opt_steps, samples_seen (from the checkpoint's meta) and ema (whether
    the checkpoint holds EMA weights).
    """
    model, ckpt = load_model(checkpoint, device, prefer_ema=prefer_ema)
    if noise_images:
        model.backbone.register_forward_pre_hook(noise_hook(NOISE_SEED))
    torch.manual_seed(0)  # any randomness in the network's forward repeats between calls
    cfg = PredictConfig(store=store, split=split, batch_size=batch_size, workers=workers, tta=tta, device=device)
    report = evaluate(model, ckpt.model_config, cfg, rayiou=rayiou, progress=False, mask=mask)
    return {"checkpoint": Path(checkpoint).name, "opt_steps": int(ckpt.meta.get("opt_steps", 0)),
            "samples_seen": int(ckpt.meta.get("samples_seen", 0)), "ema": ckpt.ema is not None,
            **report_metrics(report)}
