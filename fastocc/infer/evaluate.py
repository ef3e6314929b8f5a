"""Score a network on a store split with the model-free metric code of `occdata.eval.metrics`.

One function serves `fastocc eval` and the trainer's validation. It streams: each batch is predicted
(`predict_split`: scene order, temporal queue, optional BEV-flip TTA), reduced to uint8 labels, fed to
the accumulators and dropped, so memory does not grow with the split.

Sharded use (DDP): pass `rank`/`world_size` (or leave them None under an initialised torch.distributed);
each rank scores its own shard and returns a LOCAL report. Combine them with `reduce_reports` (lists
of reports, e.g. after `all_gather_object`) or `all_reduce_report` (sums the integer `state` arrays
with torch.distributed); the metrics are sums of counts, so the result equals a single-process run.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from fastocc.checkpoint import check_checkpoint_file, load_model
from fastocc.infer.common import check_device, split_indices
from fastocc.infer.predict import PredictConfig, predict_split
from fastocc.model.config import ModelConfig
from fastocc.storegrid import check_store_grid, check_store_rig
from occdata.errors import OccDataError
from occdata.eval.metrics import (
    MIoUAccumulator,
    MIoUResult,
    RayIoUAccumulator,
    RayIoUResult,
)
from occdata.eval.rays import scene_ray_origins
from occdata.store.reader import open_store

__all__ = ["EvalReport", "EvalRun", "MaskKind", "all_reduce_report", "evaluate", "format_report", "reduce_reports",
           "run_eval"]

MaskKind = Literal["camera", "lidar", "none"]


@dataclass(frozen=True, eq=False)
class EvalReport:
    """What `evaluate` measured (values are fractions in [0, 1]; printing multiplies by 100).

    miou: Occ3D mIoU over the split with `mask` (camera by default, the official protocol).
    rayiou: SparseOcc RayIoU (no mask), or None when not asked for.
    samples: labelled samples scored. frames: samples predicted (labelled or not).
    seconds: wall time of the whole evaluation (loading, network, metrics).
    infer_seconds: time spent producing predictions (loading + network, TTA included, metrics excluded);
    frames_per_s = frames / infer_seconds (the inference rate the command reports).
    miou_state / rayiou_state: the accumulators' int64 states (summable across ranks).
    """

    miou: MIoUResult
    rayiou: RayIoUResult | None
    samples: int
    frames: int
    seconds: float
    infer_seconds: float
    frames_per_s: float
    tta: bool
    split: str | None
    mask: str
    miou_state: np.ndarray
    rayiou_state: np.ndarray | None

    def to_json(self) -> dict[str, Any]:
        """`occdata eval --json`'s dict (values in percent) plus the inference timing."""
        from occdata.eval.evaluate import results_dict

        return results_dict(self.miou, self.rayiou, split=self.split, mask=self.mask, n_samples=self.samples,
                            unlabelled_skipped=self.frames - self.samples, seconds=round(self.seconds, 3),
                            tta=self.tta, frames=self.frames, infer_seconds=round(self.infer_seconds, 3),
                            frames_per_s=round(self.frames_per_s, 4))


def _rate(frames: int, seconds: float) -> float:
    return frames / seconds if seconds > 0 else math.nan


def _report(miou: MIoUAccumulator, ray: RayIoUAccumulator | None, **kw: Any) -> EvalReport:
    return EvalReport(
        miou=miou.result(), rayiou=ray.result() if ray is not None else None,
        frames_per_s=_rate(kw["frames"], kw["infer_seconds"]),
        miou_state=np.asarray(miou.state, dtype=np.int64).copy(),
        rayiou_state=None if ray is None else np.asarray(ray.state, dtype=np.int64).copy(), **kw,
    )


def _mask_of(batch: Any, mask: MaskKind) -> np.ndarray | None:
    if mask == "none":
        return None
    t = batch.mask_camera if mask == "camera" else batch.mask_lidar
    return t.numpy().astype(np.uint8)


def _labelled_split(reader: Any, cfg: PredictConfig) -> int:
    """The number of built samples of the split; an `OccDataError` when it has none or none labelled."""
    indices = split_indices(reader, cfg.split)  # also checks the split name before the loader starts
    if not len(indices):
        raise OccDataError(f"split {cfg.split!r} of {cfg.store} has no built samples")
    if not reader.small("labels/present")[indices].any():
        raise OccDataError(f"split {cfg.split!r} of {cfg.store} has no labelled samples: nothing to score")
    return len(indices)


def _score_batch(reader: Any, batch: Any, pred: np.ndarray, mask: MaskKind, miou_acc: MIoUAccumulator,
                 ray_acc: RayIoUAccumulator | None) -> int:
    """Add a batch's labelled samples (`pred (B, X, Y, Z) uint8`) to the accumulators; returns how many."""
    labelled = batch.has_labels.numpy()
    if not labelled.any():
        return 0
    gt = batch.semantics.numpy()[labelled].astype(np.uint8)
    m = _mask_of(batch, mask)
    miou_acc.update(gt, pred[labelled], None if m is None else m[labelled])
    if ray_acc is not None:
        for k in np.flatnonzero(labelled):
            origins = scene_ray_origins(reader, int(batch.sample_index[k]))
            ray_acc.update(gt[int(np.count_nonzero(labelled[:k]))], pred[k], origins)
    return int(labelled.sum())


@torch.no_grad()
def evaluate(
    model: nn.Module,
    model_cfg: ModelConfig,
    cfg: PredictConfig,
    rayiou: bool = True,
    progress: bool = True,
    mask: MaskKind = "camera",
    rank: int | None = None,
    world_size: int | None = None,
) -> EvalReport:
    """Predict the split of `cfg` with `model` and score it (mIoU with `mask`, RayIoU if `rayiou`).

    The model's train/eval mode is restored afterwards. Samples without labels (test split) are
    predicted but not scored; a split with no labelled sample at all is an `OccDataError` (single
    process) because there is nothing to score. Returns this rank's LOCAL report when sharded.
    """
    if mask not in ("camera", "lidar", "none"):
        raise OccDataError(f"unknown mask {mask!r} (camera, lidar or none)")
    t0 = time.perf_counter()
    reader = open_store(cfg.store)
    check_store_grid(reader, model_cfg, "eval")
    total = _labelled_split(reader, cfg)
    miou_acc = MIoUAccumulator()
    ray_acc = RayIoUAccumulator() if rayiou else None
    dist = torch.distributed
    if rank is None or world_size is None:  # the loader shards the same way (predict_split)
        on = dist.is_available() and dist.is_initialized()
        rank, world_size = (dist.get_rank(), dist.get_world_size()) if on else (0, 1)
    sharded = world_size > 1
    show = progress and rank == 0  # one bar, on rank 0 (it counts rank 0's shard when sharded)
    bar = tqdm(total=None if sharded else total, desc="eval", unit="sample", disable=not show,
               dynamic_ncols=True)
    frames = samples = 0
    infer_seconds = 0.0
    stream = predict_split(model, model_cfg, cfg, rank=rank, world_size=world_size)
    try:
        while True:
            t_in = time.perf_counter()
            try:
                batch, probs = next(stream)
            except StopIteration:
                break
            infer_seconds += time.perf_counter() - t_in
            pred = probs.argmax(1).to(torch.uint8).numpy()  # (B, X, Y, Z)
            del probs
            frames += len(batch)
            samples += _score_batch(reader, batch, pred, mask, miou_acc, ray_acc)
            bar.update(len(batch))
    finally:
        stream.close()
        bar.close()
    return _report(miou_acc, ray_acc, samples=samples, frames=frames, seconds=time.perf_counter() - t0,
                   infer_seconds=infer_seconds, tta=cfg.tta, split=cfg.split, mask=mask)


def reduce_reports(reports: Sequence[EvalReport]) -> EvalReport:
    """Combine per-rank reports into the split's report: states and counts summed, times = the slowest
    rank's (the ranks ran in parallel), frames/s = all frames over the slowest rank's inference time."""
    if not reports:
        raise ValueError("reduce_reports needs at least one report")
    r0 = reports[0]
    miou = MIoUAccumulator.from_state(np.sum([r.miou_state for r in reports], axis=0))
    ray = None
    if r0.rayiou_state is not None:
        ray = RayIoUAccumulator.from_state(np.sum([r.rayiou_state for r in reports], axis=0))
    return _report(miou, ray, samples=sum(r.samples for r in reports), frames=sum(r.frames for r in reports),
                   seconds=max(r.seconds for r in reports), infer_seconds=max(r.infer_seconds for r in reports),
                   tta=r0.tta, split=r0.split, mask=r0.mask)


def all_reduce_report(report: EvalReport, device: torch.device | str | None = None) -> EvalReport:
    """`reduce_reports` over torch.distributed (every rank gets the combined report).

    `device`: where the reduction tensors live (NCCL needs CUDA); default: the current CUDA device for
    the nccl backend, else CPU. Without an initialised process group the report is returned as is."""
    dist = torch.distributed
    if not (dist.is_available() and dist.is_initialized()):
        return report
    if device is None:
        device = torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else "cpu"
    parts = [report.miou_state.ravel()]
    if report.rayiou_state is not None:
        parts.append(report.rayiou_state.ravel())
    counts = np.array([report.samples, report.frames], dtype=np.int64)
    flat = torch.from_numpy(np.concatenate(parts + [counts])).to(device)
    times = torch.tensor([report.seconds, report.infer_seconds], dtype=torch.float64, device=device)
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    dist.all_reduce(times, op=dist.ReduceOp.MAX)
    flat_np = flat.cpu().numpy()
    n_m = report.miou_state.size
    miou = MIoUAccumulator.from_state(flat_np[:n_m].reshape(report.miou_state.shape))
    ray = None
    if report.rayiou_state is not None:
        n_r = report.rayiou_state.size
        ray = RayIoUAccumulator.from_state(flat_np[n_m:n_m + n_r].reshape(report.rayiou_state.shape))
    seconds, infer_seconds = (float(x) for x in times.cpu())
    return _report(miou, ray, samples=int(flat_np[-2]), frames=int(flat_np[-1]), seconds=seconds,
                   infer_seconds=infer_seconds, tta=report.tta, split=report.split, mask=report.mask)


@dataclass(frozen=True)
class EvalRun:
    """`fastocc eval` options: a checkpoint scored on a store split."""

    checkpoint: Path
    predict: PredictConfig
    rayiou: bool = True
    mask: MaskKind = "camera"
    progress: bool = True
    prefer_ema: bool = True


def run_eval(run: EvalRun) -> EvalReport:
    """`fastocc eval`: load the checkpoint (its own model config) and `evaluate` it.

    Under torchrun (WORLD_SIZE > 1) the processes join a process group, each scores its shard (whole
    scenes, so temporal queues are intact) and every rank returns the combined report."""
    from fastocc import dist as D

    check_checkpoint_file(run.checkpoint)  # a mistyped checkpoint is said first
    check_device(run.predict.device)
    split_indices(run.predict.store, run.predict.split)  # unknown split / bad store before loading weights
    dist = torch.distributed
    joined = not (dist.is_available() and dist.is_initialized())  # leave a caller's own group alone
    info = D.setup(run.predict.device)
    try:
        # cuda:LOCAL_RANK under torchrun; "auto" as resolved
        chosen = info.enabled or run.predict.device == "auto"
        cfg = replace(run.predict, device=str(info.device)) if chosen else run.predict
        model, ckpt = load_model(run.checkpoint, device=cfg.device, prefer_ema=run.prefer_ema)
        check_store_rig(cfg.store, ckpt.cameras, ckpt.model_config.num_cams, str(run.checkpoint), "eval")
        report = evaluate(model, ckpt.model_config, cfg, rayiou=run.rayiou, progress=run.progress and info.is_main,
                          mask=run.mask)
        return all_reduce_report(report, info.device) if info.enabled else report
    finally:
        if joined:
            D.teardown(info)


def format_report(report: EvalReport) -> str:
    """`occdata eval`'s per-class table and summary line, plus the inference rate."""
    from occdata.eval.evaluate import EvalReport as FileEvalReport
    from occdata.eval.evaluate import format_table, summary_line

    lines = [format_table(report.miou, report.rayiou)]
    if report.frames > report.samples:
        lines.append(f"({report.frames - report.samples} unlabelled '{report.split}' samples skipped)")
    summary = summary_line(FileEvalReport(
        split=str(report.split), mask=report.mask, n_samples=report.samples,
        n_unlabelled_skipped=report.frames - report.samples, miou=report.miou, rayiou=report.rayiou,
        seconds=report.seconds))
    tta = " with TTA" if report.tta else ""
    lines.append(f"{summary}; inference{tta} {report.frames_per_s:.2f} frames/s")
    return "\n".join(lines)
