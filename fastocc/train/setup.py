"""Set-up of a training process: the fixed `Run` context, the run folder, model, losses, loader, log.

`loop.py` drives training with these; nothing here changes during a run.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from fastocc import dist as D
from fastocc.checkpoint import (
    CheckpointError,
    checkpoint_cameras,
    first_mismatch,
    load_checkpoint,
    load_weights,
    model_config_from_dict,
)
from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader
from fastocc.losses import LossConfig, LossTargets, class_weights_from_counts, occupancy_loss
from fastocc.model import FastOcc
from fastocc.model.config import ModelConfig
from fastocc.model.inputs import synthetic_inputs
from fastocc.model.noise import noise_hook
from fastocc.storegrid import check_store_grid, check_store_rig
from fastocc.train.config import TrainConfig, flat_config, incompatible_fields
from fastocc.train.preempt import StopRequest
from fastocc.train.state import EMA, TrainState, class_counts, load_resume
from occdata.constants import CAMERA_ORDER, FREE_LABEL
from occdata.errors import OccDataError
from occdata.fileio import write_atomic
from occdata.store.layout import store_rig
from occdata.store.reader import open_store
from occdata.store.splits import store_default_split
from occdata.text import plural

__all__ = ["MetricsLog", "Run", "StepPace", "build_model", "check_writable", "estimate_step_seconds", "init_from",
           "loader_config", "loss_config", "make_run", "new_state", "pace_message", "prepare_out",
           "say_start", "take_store_rig", "take_val_split"]


@dataclass
class StepPace:
    """The pace of this process's first warm optimizer steps, said once after them: wall seconds per step over
    steps 2 .. 1 + n of an epoch (data loading included). The first step of a process is slow (allocator,
    caches, worker start), so the start-up estimate alone can be several times off."""

    max_steps: int = 5
    said: bool = False
    _count: int = 0
    _t0: float = 0.0

    def start_epoch(self) -> None:
        self._count = 0  # an epoch boundary (validation, saving) must not count as step time

    def tick(self, steps_in_epoch: int) -> float | None:
        """After each optimizer step: the measured seconds per step once enough warm steps were seen, else None."""
        if self.said:
            return None
        self._count += 1
        n = min(self.max_steps, steps_in_epoch - 1)
        if self._count == 1:
            self._t0 = time.perf_counter()
            return None
        if n < 1 or self._count < n + 1:
            return None
        self.said = True
        return (time.perf_counter() - self._t0) / n


# -- what does not change during a run ------------------------------------------------------------------
@dataclass
class Run:
    """The fixed parts of one training process (rank): config, devices, batch split, loss, loader, logger."""

    cfg: TrainConfig
    info: D.DistInfo
    model_cfg: ModelConfig
    micro: int  # samples per forward pass on this rank
    accum: int  # micro-batches per optimizer step
    show_progress: bool
    say: Callable[[str], None]
    stop: StopRequest
    loss_cfg: LossConfig | None = None
    loader_cfg: LoaderConfig | None = None
    samples_per_epoch: int = 0
    logger: MetricsLog | None = None
    model: nn.Module | None = None  # what the step calls: the DDP wrapper under torchrun, else the raw network
    cameras: tuple[str, ...] = CAMERA_ORDER  # the store's camera order (`take_store_rig`), recorded in checkpoints
    pace: StepPace = field(default_factory=StepPace)

    @property
    def out(self) -> Path:
        return Path(self.cfg.out)

    @property
    def use_amp(self) -> bool:
        return self.cfg.amp and self.info.device.type == "cuda"

    def epoch_loader(self, epoch: int, skip: int) -> torch.utils.data.DataLoader:
        cfg = dataclasses.replace(self.loader_cfg, skip_batches=skip)
        loader = make_loader(cfg, num_workers=self.cfg.workers, pin_memory=self.info.device.type == "cuda")
        loader.dataset.set_epoch(epoch)
        return loader


def make_run(cfg: TrainConfig, info: D.DistInfo, progress: bool, stop: StopRequest) -> Run:
    world = info.world_size
    if cfg.batch_size % world:
        raise OccDataError(f"batch_size {cfg.batch_size} (global) is not divisible by the {world} processes")
    per_rank = cfg.batch_size // world
    micro = cfg.micro_batch or per_rank
    if per_rank % micro:
        raise OccDataError(f"micro_batch {micro} does not divide the per-process batch {per_rank}")
    from tqdm import tqdm

    say = (lambda msg: tqdm.write(msg)) if info.is_main else (lambda msg: None)
    return Run(cfg=cfg, info=info, model_cfg=cfg.model_config(), micro=micro, accum=per_rank // micro,
               show_progress=progress and info.is_main, say=say, stop=stop)


# -- set-up ----------------------------------------------------------------------------------------------
def prepare_out(run: Run, resume: bool) -> dict[str, Any] | None:
    """Check the run folder (rank 0 holds its lock); return the resume payload when resuming."""
    last = run.out / "last.pt"
    if run.info.is_main and not resume and last.exists():
        raise OccDataError(f"{run.out} already holds a run (last.pt); pass --resume to continue it "
                           "or choose another --out")
    D.barrier(run.info)
    if not resume:
        return None
    if not last.exists():
        raise OccDataError(f"--resume: no checkpoint {last} to resume from")
    payload = load_resume(last)
    bad = incompatible_fields(payload["train_config"], run.cfg)
    if bad:
        saved, now = flat_config(payload["train_config"]), flat_config(run.cfg.to_dict())
        diffs = ", ".join(f"{k}: {saved.get(k)!r} -> {now.get(k)!r}" for k in bad)
        grow = " (epochs may only grow)" if "epochs" in bad else ""
        raise OccDataError(f"--resume with an incompatible config ({diffs}){grow}; these fields must match the run "
                           f"in {run.out} (start a new --out to change them)")
    return payload


def take_store_rig(run: Run, payload: dict[str, Any] | None) -> None:
    """The network's cameras are the store's: `run.model_cfg.num_cams` and `run.cameras` from its rig. A
    resumed run must find the rig it was trained on (the store may be moved, not changed): one line if not."""
    reader = open_store(run.cfg.store)
    run.cameras = tuple(store_rig(reader.attrs)["cameras"])
    run.model_cfg = run.model_cfg.replace(num_cams=len(run.cameras))
    if payload is not None:
        saved = model_config_from_dict(json.loads(payload["model_config"])).num_cams
        check_store_rig(reader, checkpoint_cameras(payload, saved), saved, f"--resume {run.out / 'last.pt'}", "train")


def take_val_split(run: Run) -> str | None:
    """`val_split` unset: the store's `val`, else its only split (a one-scene world has only `train`), put
    into `run.cfg`; returns the line that says so when it is not `val`. Nothing to choose without validation."""
    if run.cfg.val_split is not None or run.cfg.val_every == 0:
        return None
    chosen = store_default_split(run.cfg.store, "val_split in a --config TOML")
    run.cfg = dataclasses.replace(run.cfg, val_split=chosen.split)
    return None if chosen.note is None else f"validation: {chosen.note}"


def build_model(run: Run) -> nn.Module:
    cfg = run.cfg
    torch.manual_seed(cfg.seed)  # same initial weights on every rank and every start
    model = FastOcc(run.model_cfg)
    if cfg.pretrained:
        if not Path(cfg.pretrained).is_file():
            raise OccDataError(f"--pretrained {cfg.pretrained}: no such file")
        run.say(model.load_pretrained_backbone(cfg.pretrained))
    if cfg.checkpoint_backbone:
        inner = model.backbone.forward
        # Recompute the backbone's activations in backward instead of storing them (memory).
        model.backbone.forward = lambda x: torch.utils.checkpoint.checkpoint(inner, x, use_reentrant=False)
    if cfg.noise_images:
        model.backbone.register_forward_pre_hook(noise_hook(cfg.seed + 1000 * run.info.rank))
    return model.to(run.info.device)


def loss_config(run: Run) -> LossConfig:
    c, info = run.cfg, run.info
    check_store_grid(c.store, run.model_cfg)
    weights = None
    if c.class_weights:
        counts = None
        if info.is_main:
            counts = class_counts(c.store, c.train_split, c.camera_mask, run.out / "class_counts.json")
        counts = D.broadcast_object(counts, info)
        weights = tuple(float(w) for w in class_weights_from_counts(np.maximum(counts, 1)))
    elif info.is_main:
        class_counts(c.store, c.train_split, c.camera_mask, None)  # still checks the split has labels
    if c.val_every > 0 and info.is_main:
        check_val_split(c.store, c.val_split)
    w = c.loss
    return LossConfig(focal=w.focal, sem_scal=w.sem_scal, geo_scal=w.geo_scal, dice=w.dice, lovasz=w.lovasz,
                      depth=w.depth, bev=w.bev, use_camera_mask=c.camera_mask, class_weights=weights)


def check_val_split(store: str, split: str) -> None:
    """One line at the start, not after the first epoch, when validation has no labelled samples."""
    reader = open_store(store)
    counts = {s: len(reader.split_indices(s, labelled=True)) for s in reader.attrs.get("splits", [])}
    if not counts.get(split):
        raise OccDataError(f"validation split {split!r} has no labelled samples in {store} (its splits, labelled "
                           f"samples: {counts}); set val_split, or val_every = 0 to train without validation, "
                           "in a --config TOML, or rebuild with occdata build --split-file FILE")


def trains_sequentially(cfg: TrainConfig) -> bool:
    """Temporal models (and the history ablation's single-frame row) walk scenes in order."""
    return cfg.model_config().num_history > 0 or cfg.scene_sequential


def loader_config(run: Run) -> LoaderConfig:
    H, W = run.model_cfg.input_hw
    aug, sequential = run.cfg.augment, trains_sequentially(run.cfg)
    sample = SampleConfig(image=ImageAugConfig(height=H, width=W, train=aug), bev=BevAugConfig(train=aug))
    return LoaderConfig(store=run.cfg.store, batch_size=run.micro, sequential=sequential, sample=sample,
                        splits=(run.cfg.train_split,), seed=run.cfg.seed, rank=run.info.rank,
                        world_size=run.info.world_size, pad=run.info.enabled and not sequential,
                        equal_lanes=sequential,  # equal step counts on every rank (order.py)
                        limit_samples=run.cfg.limit_train_samples)


def new_state(run: Run, model: nn.Module) -> TrainState:
    cfg = run.cfg
    decay, no_decay = [], []
    for name, p in model.named_parameters():
        (no_decay if p.ndim <= 1 or name.endswith(".bias") else decay).append(p)  # no decay on norms/biases
    optimizer = torch.optim.AdamW([{"params": decay, "weight_decay": cfg.weight_decay},
                                   {"params": no_decay, "weight_decay": 0.0}], lr=cfg.peak_lr())
    return TrainState(model=model, optimizer=optimizer, ema=EMA(model, cfg.ema_decay) if cfg.ema else None)


def init_from(state: TrainState, path: str) -> None:
    """Start from another run's weights: the model, and the EMA when both keep one (else EMA = the model)."""
    ckpt = load_checkpoint(path)
    if state.ema is not None and ckpt.ema is not None:
        bad = first_mismatch(state.model.state_dict(), ckpt.ema)
        if bad is not None:
            raise CheckpointError(f"{path}: EMA weights do not fit the model config (first difference at {bad})")
    load_weights(state.model, ckpt.model, path)
    if state.ema is not None:
        state.ema.load_state_dict(ckpt.ema if ckpt.ema is not None else ckpt.model, 0)  # new run: the ramp restarts


def estimate_step_seconds(run: Run, model: nn.Module) -> float:
    """Time one forward + backward of a synthetic micro-batch; weights and buffers are restored.

    The first pass only warms up (allocator, lazy caches: it took 2-3x a training step); the second is timed.
    A first guess only: the trainer says the measured pace (`StepPace`) after the first warm steps.
    """
    saved = {k: v.clone() for k, v in model.state_dict().items()}
    dev = run.info.device
    inputs = synthetic_inputs(run.micro, run.model_cfg.input_hw, run.model_cfg.num_cams, seed=0, device=str(dev))
    X, Y, Z = run.model_cfg.fine_grid.shape
    targets = LossTargets(voxel_labels=torch.full((run.micro, X, Y, Z), FREE_LABEL, device=dev),
                          mask_camera=torch.ones(run.micro, X, Y, Z, dtype=torch.bool, device=dev))
    dt = 0.0
    for _ in range(2):
        t0 = time.perf_counter()
        out = model(inputs)
        loss, _ = occupancy_loss(out.voxel_logits.float(), targets, run.loss_cfg, None, out.bev_logits)
        loss.backward()
        dt = time.perf_counter() - t0
        model.zero_grad(set_to_none=True)
    model.load_state_dict(saved)
    model.clear_caches()
    return dt


def pace_message(s_per_step: float, warm_steps: int, steps_per_epoch: int) -> str:
    """The line said after the first warm steps."""
    return (f"measured pace: {s_per_step:.2f} s per optimizer step (steps 2-{warm_steps + 1} of this run, data "
            f"loading included): ~{s_per_step * steps_per_epoch / 60:.1f} min per epoch of {steps_per_epoch} steps")


class MetricsLog:
    """metrics.jsonl (+ TensorBoard when installed); rank 0 only."""

    def __init__(self, out: Path, enabled: bool, resume_step: int | None) -> None:
        self.enabled = enabled
        self.path = out / "metrics.jsonl"
        self.tb = None
        if not enabled:
            return
        if resume_step is not None and self.path.exists():
            # Drop records written after the checkpoint we resume from (they will be written again).
            keep = [ln for ln in self.path.read_text().splitlines()
                    if ln.strip() and json.loads(ln).get("opt_step", 0) <= resume_step]
            write_atomic(self.path, "".join(ln + "\n" for ln in keep).encode())
        try:
            from torch.utils.tensorboard import SummaryWriter  # optional extra: pip install fastocc[tensorboard]

            self.tb = SummaryWriter(str(out / "tb"))
        except ImportError:
            self.tb = None

    def write(self, record: dict[str, Any]) -> None:
        if not self.enabled:
            return
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        if self.tb is not None:
            kind, step = record.get("kind", "train"), record.get("opt_step", 0)
            for k, v in record.items():
                if isinstance(v, int | float) and not isinstance(v, bool) and k not in ("opt_step", "epoch"):
                    self.tb.add_scalar(f"{kind}/{k}", v, step)
            self.tb.flush()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{time.time_ns()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise OccDataError(f"run folder {out} is not writable ({exc.strerror or exc}); choose another --out") from None


def say_start(run: Run) -> None:
    cfg, info = run.cfg, run.info
    run.say(f"fastocc train: preset {cfg.preset} head {cfg.head} input {run.model_cfg.input_hw} history "
            f"{run.model_cfg.num_history} on {info.world_size} x {info.device}; {run.samples_per_epoch} training "
            f"samples/epoch, {plural(cfg.epochs, 'epoch')}")
    run.say(f"learning rate: {cfg.lr:g} x {cfg.lr_scaling} scaling ({cfg.batch_size} global batch / "
            f"{cfg.lr_base_batch}) = {cfg.peak_lr():.3g} peak; warm-up {cfg.warmup_epochs:g} epochs, cosine to "
            f"{cfg.min_lr_ratio:g} x peak; {plural(run.accum, 'accumulation step')} of {run.micro} per process")


