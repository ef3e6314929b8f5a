"""The training loop: one readable function per concern (set-up, one step, one epoch, validation, saving).

Exact resume: a checkpoint is written only at optimizer-step boundaries and holds everything the next
step depends on (weights, AdamW moments, EMA, samples seen -> learning rate, RNG states, temporal
queue, epoch and micro-batch position). The epoch's sample order is a pure function of (seed, epoch)
and the loader starts the epoch at batch k without decoding the skipped samples (`skip_batches`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader
from fastocc.data.batch import Batch
from fastocc.data.order import Slot, sequential_batches, shuffle_units
from fastocc.data.workers import start_iteration
from fastocc.losses import LossConfig, LossTargets, class_weights_from_counts, occupancy_loss
from fastocc.model import FastOcc
from fastocc.model.config import DepthBins, ModelConfig
from fastocc.model.inputs import synthetic_inputs
from fastocc.train import dist as D
from fastocc.train.config import TrainConfig, config_to_toml, incompatible_fields
from fastocc.train.state import (
    EMA,
    class_counts,
    get_rng_state,
    load_resume,
    save_train_checkpoint,
    set_rng_state,
)
from occdata.errors import OccDataError

__all__ = ["NonFiniteLossError", "TrainResult", "depth_onehot", "train"]


class NonFiniteLossError(OccDataError):
    """Too many non-finite losses in a row; the last good checkpoint is kept."""


@dataclass(frozen=True)
class TrainResult:
    out: Path
    epochs_done: int
    opt_steps: int
    best_miou: float | None
    interrupted: bool = False


def depth_onehot(depth: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Depth targets `(B, N, h, w)` metres (0 = none) -> one-hot bins `(B*N, D, h, w) float32`
    (all-zero where there is no target or the depth is outside [lower, upper))."""
    d = depth.flatten(0, 1)
    k = torch.floor((d - bins.lower) / bins.step).long()
    valid = (d > 0) & (k >= 0) & (k < bins.count)
    return (F.one_hot(k.clamp(0, bins.count - 1), bins.count) * valid[..., None]).permute(0, 3, 1, 2).float()


def _noise_hook(seed: int):
    """Forward pre-hook for the backbone: its input images become Gaussian noise (the image ablation)."""
    gen = torch.Generator().manual_seed(seed)

    def hook(module: nn.Module, args: tuple) -> tuple:
        (x,) = args
        return (torch.randn(x.shape, generator=gen).to(x),)

    return hook


class _Run:
    """State of one training process (rank). `train()` drives it."""

    def __init__(self, cfg: TrainConfig, info: D.DistInfo, progress: bool) -> None:
        self.cfg, self.info = cfg, info
        self.progress = progress and info.is_main
        self.out = Path(cfg.out)
        self.model_cfg: ModelConfig = cfg.model_config()
        world = info.world_size
        if cfg.batch_size % world:
            raise OccDataError(f"batch_size {cfg.batch_size} (global) is not divisible by the {world} processes")
        per_rank = cfg.batch_size // world
        self.micro = cfg.micro_batch or per_rank
        if per_rank % self.micro:
            raise OccDataError(f"micro_batch {self.micro} does not divide the per-process batch {per_rank}")
        self.accum = per_rank // self.micro
        self.sequential = self.model_cfg.num_history > 0 or cfg.scene_sequential
        self.use_amp = cfg.amp and info.device.type == "cuda"

    # -- set-up -------------------------------------------------------------------------------
    def prepare_out(self, resume: bool) -> dict[str, Any] | None:
        """Create/check the run folder (rank 0 writes); return the resume payload if resuming."""
        last = self.out / "last.pt"
        if self.info.is_main:
            try:
                self.out.mkdir(parents=True, exist_ok=True)
                probe = self.out / f".write-test-{os.getpid()}"
                probe.write_bytes(b"")
                probe.unlink()
            except OSError as exc:
                raise OccDataError(f"run folder {self.out} is not writable ({exc.strerror or exc}); "
                                   "choose another --out") from None
            if not resume and last.exists():
                raise OccDataError(f"{self.out} already holds a run (last.pt); pass --resume to continue it "
                                   "or choose another --out")
        D.barrier(self.info)
        if not resume:
            return None
        if not last.exists():
            raise OccDataError(f"--resume: no checkpoint {last} to resume from")
        payload = load_resume(last)
        bad = incompatible_fields(payload["train_config"], self.cfg)
        if bad:
            saved = payload["train_config"]
            diffs = ", ".join(f"{k}: {saved.get(k)!r} -> {self.cfg.to_dict().get(k)!r}" for k in bad)
            raise OccDataError(f"--resume with an incompatible config ({diffs}); these fields must match the run "
                               f"in {self.out} (start a new --out to change them)")
        return payload

    def build_model(self) -> nn.Module:
        torch.manual_seed(self.cfg.seed)  # same initial weights on every rank and every start
        model = FastOcc(self.model_cfg)
        if self.cfg.pretrained:
            if not Path(self.cfg.pretrained).is_file():
                raise OccDataError(f"--pretrained {self.cfg.pretrained}: no such file")
            model.load_pretrained_backbone(self.cfg.pretrained)
        if self.cfg.checkpoint_backbone:
            inner = model.backbone.forward
            # Recompute the backbone's activations in backward instead of storing them (memory).
            model.backbone.forward = lambda x: torch.utils.checkpoint.checkpoint(inner, x, use_reentrant=False)
        if self.cfg.noise_images:
            model.backbone.register_forward_pre_hook(_noise_hook(self.cfg.seed + 1000 * self.info.rank))
        return model.to(self.info.device)

    def loss_config(self) -> LossConfig:
        c = self.cfg
        weights = None
        if c.class_weights:
            cache = self.out / "class_counts.json"
            counts = None
            if self.info.is_main:
                counts = class_counts(c.store, c.train_split, c.camera_mask, cache)
            counts = D.broadcast_object(counts, self.info)
            weights = tuple(float(w) for w in class_weights_from_counts(np.maximum(counts, 1)))
        elif self.info.is_main:
            class_counts(c.store, c.train_split, c.camera_mask, None)  # still checks the split has labels
        return LossConfig(focal=c.w_focal, sem_scal=c.w_sem_scal, geo_scal=c.w_geo_scal, dice=c.w_dice,
                          lovasz=c.w_lovasz, depth=c.w_depth, bev=c.w_bev, use_camera_mask=c.camera_mask,
                          class_weights=weights)

    def loader_config(self) -> LoaderConfig:
        H, W = self.model_cfg.input_hw
        aug = self.cfg.augment
        sample = SampleConfig(image=ImageAugConfig(height=H, width=W, train=aug), bev=BevAugConfig(train=aug))
        return LoaderConfig(store=self.cfg.store, batch_size=self.micro, sequential=self.sequential, sample=sample,
                            splits=(self.cfg.train_split,), seed=self.cfg.seed, rank=self.info.rank,
                            world_size=self.info.world_size, pad=self.info.enabled and not self.sequential,
                            equal_lanes=self.sequential)  # equal step counts on every rank (order.py)

    def make_epoch_loader(self, epoch: int, skip: int) -> torch.utils.data.DataLoader:
        cfg = dataclasses.replace(self.loader_cfg, skip_batches=skip)
        loader = make_loader(cfg, num_workers=self.cfg.workers, pin_memory=self.info.device.type == "cuda")
        self._limit(loader.dataset)
        loader.dataset.set_epoch(epoch)
        return loader

    def _limit(self, ds) -> None:
        if self.cfg.limit_train_samples:
            ds.indices = ds.indices[: self.cfg.limit_train_samples]

    def batches_per_epoch(self, ds, epoch: int) -> int:
        """Micro-batches this rank yields in an epoch (each worker batches its own share)."""
        n_workers = max(1, self.cfg.workers)
        total = 0
        for w in range(n_workers):
            slot = Slot(self.info.rank, self.info.world_size, w, n_workers)
            if self.sequential:
                total += len(sequential_batches(ds.indices, ds.samples().scene_index, slot, self.micro,
                                                self.cfg.seed, epoch, equal_lanes=self.loader_cfg.equal_lanes))
            else:
                units = shuffle_units(ds.indices, ds.samples().block, slot, self.cfg.seed, epoch,
                                      pad=self.loader_cfg.pad)
                total += -(-sum(len(u) for u in units) // self.micro)
        return total

    def estimate_step_seconds(self, model: nn.Module, loss_cfg: LossConfig) -> float:
        """Time one forward + backward of a synthetic micro-batch; weights and buffers are restored.

        The first pass only warms up (allocator, lazy caches: it took 2-3x a training step); the second is timed.
        """
        saved = {k: v.clone() for k, v in model.state_dict().items()}
        inputs = synthetic_inputs(self.micro, self.model_cfg.input_hw, self.model_cfg.num_cams, seed=0,
                                  device=str(self.info.device))
        X, Y, Z = self.model_cfg.fine_grid.shape
        targets = LossTargets(voxel_labels=torch.full((self.micro, X, Y, Z), 17, device=self.info.device),
                              mask_camera=torch.ones(self.micro, X, Y, Z, dtype=torch.bool, device=self.info.device))
        dt = 0.0
        for _ in range(2):
            t0 = time.perf_counter()
            out = model(inputs)
            loss, _ = occupancy_loss(out.voxel_logits.float(), targets, loss_cfg, None, out.bev_logits)
            loss.backward()
            dt = time.perf_counter() - t0
            model.zero_grad(set_to_none=True)
        model.load_state_dict(saved)
        model.clear_caches()
        return dt


def _keep_masked(logits: torch.Tensor, targets: LossTargets) -> tuple[torch.Tensor, LossTargets]:
    """Select the camera-masked voxels ONCE: logits `(1, C, V, 1, 1)`, labels `(1, V, 1, 1)`, no mask.

    The voxel losses treat a batch as one bag of voxels, so this equals passing the mask to each of
    them, but autograd scatters one masked gradient back instead of one per loss term (~1 s/step on CPU).
    """
    keep = targets.mask_camera.bool()
    C = logits.shape[1]
    x = logits.movedim(1, -1)[keep]  # (V, C)
    y = targets.voxel_labels[keep]
    return x.t().reshape(1, C, -1, 1, 1), dataclasses.replace(targets, voxel_labels=y.reshape(1, -1, 1, 1),
                                                              mask_camera=None)


def _targets(batch: Batch, model_cfg: ModelConfig) -> LossTargets:
    if not bool(batch.has_labels.all()):
        bad = batch.sample_index[~batch.has_labels].tolist()
        raise OccDataError(f"training samples {bad} have no labels; training needs a labelled split")
    return LossTargets(voxel_labels=batch.semantics, mask_camera=batch.mask_camera,
                       depth_onehot=depth_onehot(batch.depth_target, model_cfg.depth_bins),
                       bev_multihot=batch.bev_target)


def _cpu_seconds() -> float:
    """CPU time of this process and its finished children (loader workers of past epochs)."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _data_iter(loader) -> Iterator[tuple[Batch, float]]:
    """Batches with the seconds spent waiting for each.

    Ctrl-C is held back while the workers start (`start_iteration`). Closing the generator (Ctrl-C in
    the loop body) shuts the workers down at once.
    """
    it = None
    try:
        it = start_iteration(loader)
        while True:
            t0 = time.perf_counter()
            try:
                batch = next(it)
            except StopIteration:
                return
            yield batch, time.perf_counter() - t0
    finally:
        del it  # the only reference: torch's iterator joins (or terminates) its workers now


class _Logger:
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
            self.path.write_text("".join(ln + "\n" for ln in keep))
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


def _evaluate_fns():
    """The shared evaluation (`fastocc.infer.evaluate`), or None where this install lacks it."""
    try:
        from fastocc.infer.evaluate import all_reduce_report, evaluate
    except ImportError:
        return None
    return evaluate, all_reduce_report


def _report_dict(report: Any) -> dict[str, float]:
    """mIoU (camera mask), geometric IoU, RayIoU and frames/s of an EvalReport as fractions."""
    out = {"miou": float(report.miou.miou), "geo_iou": float(report.miou.geo_iou),
           "frames_per_s": float(report.frames_per_s)}
    if report.rayiou is not None:
        out["rayiou"] = float(report.rayiou.rayiou)
    return out


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> TrainResult:
    """Train (or continue with `resume`) as described by `cfg`; returns when done or interrupted (Ctrl-C).

    Under torchrun each process calls this; rank 0 writes the run folder."""
    info = D.setup(cfg.device)
    try:
        return _train(cfg, info, resume, progress)
    finally:
        D.teardown(info)


def _train(cfg: TrainConfig, info: D.DistInfo, resume: bool, progress: bool) -> TrainResult:
    from tqdm import tqdm

    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.deterministic:
        torch.use_deterministic_algorithms(True)
    run = _Run(cfg, info, progress)
    say = (lambda msg: tqdm.write(msg)) if info.is_main else (lambda msg: None)
    payload = run.prepare_out(resume)
    if info.is_main:
        (run.out / "config.toml").write_text(config_to_toml(cfg))
        (run.out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")

    model = run.build_model()
    raw_model = model
    loss_cfg = run.loss_config()
    run.loader_cfg = run.loader_config()
    probe_ds = make_loader(run.loader_cfg, num_workers=0).dataset
    run._limit(probe_ds)
    n_train = len(probe_ds)
    if n_train == 0:
        raise OccDataError(f"no built samples in the {cfg.train_split!r} split of {cfg.store}")
    samples_per_epoch = n_train
    ema = EMA(raw_model, cfg.ema_decay) if cfg.ema else None
    decay, no_decay = [], []
    for name, p in raw_model.named_parameters():
        (no_decay if p.ndim <= 1 or name.endswith(".bias") else decay).append(p)  # no decay on norms/biases
    optimizer = torch.optim.AdamW([{"params": decay, "weight_decay": cfg.weight_decay},
                                   {"params": no_decay, "weight_decay": 0.0}], lr=cfg.peak_lr())

    say(f"fastocc train: preset {cfg.preset} head {cfg.head} input {run.model_cfg.input_hw} history "
        f"{run.model_cfg.num_history} on {info.world_size} x {info.device}; {n_train} training samples/epoch, "
        f"{cfg.epochs} epochs")
    say(f"learning rate: {cfg.lr:g} x {cfg.lr_scaling} scaling ({cfg.batch_size} global batch / "
        f"{cfg.lr_base_batch}) = {cfg.peak_lr():.3g} peak; warm-up {cfg.warmup_epochs:g} epochs, cosine to "
        f"{cfg.min_lr_ratio:g} x peak; {run.accum} accumulation step(s) of {run.micro} per process")

    epoch, pos, samples_seen, opt_steps, best = 0, 0, 0, 0, None
    nonfinite_run = 0
    if payload is not None:
        raw_model.load_state_dict(payload["model"])
        optimizer.load_state_dict(payload["optimizer"])
        if ema is not None:
            if payload.get("ema") is None:
                raise OccDataError("--resume: the checkpoint has no EMA weights but ema = true")
            ema.state = {k: v.to(info.device) for k, v in payload["ema"].items()}
            ema.updates = int(payload["ema_updates"])
        prog = payload["progress"]
        epoch, pos, samples_seen, opt_steps = (int(prog[k]) for k in ("epoch", "pos", "samples_seen", "opt_steps"))
        best = prog.get("best_miou")
        nonfinite_run = int(prog.get("nonfinite_run", 0))
        set_rng_state(payload["rng"][info.rank] if info.rank < len(payload["rng"]) else payload["rng"][0])
        queue = payload.get("temporal_queue")
        if queue is not None and raw_model.temporal is not None:
            t = raw_model.temporal
            t._feats, t._poses, t._bev_aug = (None if v is None else v.to(info.device) for v in queue)
        say(f"resuming {run.out / 'last.pt'}: epoch {epoch + 1} at micro-batch {pos}, {opt_steps} steps done")
    logger = _Logger(run.out, info.is_main, opt_steps if payload is not None else None)

    per_epoch = run.batches_per_epoch(probe_ds, epoch)
    if info.device.type == "cpu" and info.is_main:
        dt = run.estimate_step_seconds(raw_model, loss_cfg)
        say(f"estimated time per epoch on CPU: ~{dt * per_epoch / 60:.1f} min ({per_epoch} micro-batches x "
            f"{dt:.2f} s forward+backward, measured on one synthetic batch; data loading not included)")
    D.barrier(info)
    if info.enabled:  # wrap after the time estimate: DDP's gradient hooks must see only real steps
        model = nn.parallel.DistributedDataParallel(
            raw_model, device_ids=[info.device.index] if info.device.type == "cuda" else None,
            find_unused_parameters=True)  # e.g. the ResNet fc layer is never used

    def checkpoint(path: Path, meta_extra: dict[str, Any] | None = None) -> None:
        rng = [get_rng_state()]
        if info.enabled:
            gathered: list[Any] = [None] * info.world_size
            torch.distributed.all_gather_object(gathered, rng[0])
            rng = gathered
        if not info.is_main:
            return
        t = raw_model.temporal
        queue = None if t is None or t._feats is None else [v.detach().cpu() for v in (t._feats, t._poses, t._bev_aug)]
        progress_state = {"epoch": epoch, "pos": pos, "samples_seen": samples_seen, "opt_steps": opt_steps,
                          "best_miou": best, "nonfinite_run": nonfinite_run}
        meta = {"epoch": epoch, "opt_steps": opt_steps, "samples_seen": samples_seen, **(meta_extra or {})}
        try:
            save_train_checkpoint(path, run.model_cfg, raw_model, ema, meta, optimizer=optimizer.state_dict(),
                                  ema_updates=0 if ema is None else ema.updates, progress=progress_state, rng=rng,
                                  train_config=cfg.to_dict(), temporal_queue=queue)
        except OSError as exc:
            raise OccDataError(f"could not write checkpoint {path} ({exc.strerror or exc}); the previous "
                               "checkpoint there is intact") from None

    loss_fn = occupancy_loss  # looked up at start (tests patch the module attribute)
    interrupted = False
    grad_ctx = contextlib.nullcontext
    micro_i = 0
    data: Iterator[tuple[Batch, float]] | None = None
    try:
        while epoch < cfg.epochs:
            loader = run.make_epoch_loader(epoch, pos)
            per_epoch = run.batches_per_epoch(probe_ds, epoch)
            bar = tqdm(total=per_epoch, initial=pos, desc=f"epoch {epoch + 1}/{cfg.epochs}", disable=not run.progress,
                       dynamic_ncols=True, unit="batch")
            model.train()
            t_epoch, wait_epoch, loss_sum, loss_n = time.perf_counter(), 0.0, 0.0, 0
            t_log, wait_log, samples_log = time.perf_counter(), 0.0, 0
            micro_i, acc_loss, acc_terms, acc_n, acc_idx = 0, 0.0, {}, 0, []
            acc_finite = True
            data = _data_iter(loader)
            for batch, wait in data:
                wait_epoch += wait
                wait_log += wait
                batch = batch.to(info.device, non_blocking=True)
                last_micro = micro_i == run.accum - 1
                sync = model.no_sync if info.enabled and not last_micro else grad_ctx
                with sync():
                    with torch.autocast(device_type=info.device.type, dtype=torch.bfloat16, enabled=run.use_amp):
                        out = model(batch.inputs())
                    logits, targets = out.voxel_logits.float(), _targets(batch, run.model_cfg)
                    if loss_cfg.use_camera_mask:
                        logits, targets = _keep_masked(logits, targets)
                    total, terms = loss_fn(logits, targets, dataclasses.replace(loss_cfg, use_camera_mask=False),
                                           out.depth_probs.float(),
                                           None if out.bev_logits is None else out.bev_logits.float())
                    (total * (len(batch) / (run.micro * run.accum))).backward()
                acc_finite &= bool(torch.isfinite(total))
                acc_loss += float(total.detach()) * len(batch)
                for k, v in terms.items():
                    acc_terms[k] = acc_terms.get(k, 0.0) + float(v) * len(batch)
                acc_n += len(batch)
                acc_idx += batch.sample_index.tolist()
                micro_i += 1
                pos += 1
                bar.update(1)
                if micro_i < run.accum and pos < per_epoch:
                    continue
                # -- optimizer step (all ranks agree on skipping) --------------------------------
                lr = cfg.lr_at(samples_seen, samples_per_epoch)
                for g in optimizer.param_groups:
                    g["lr"] = lr
                grad_norm = (nn.utils.clip_grad_norm_(raw_model.parameters(), cfg.grad_clip) if cfg.grad_clip
                             else torch.zeros(()))
                ok = acc_finite and bool(torch.isfinite(grad_norm))
                stats = D.all_reduce_sum(torch.tensor([acc_loss, float(acc_n), 0.0 if ok else 1.0],
                                                      dtype=torch.float64), info)
                n_global = int(stats[1])
                if stats[2] > 0:
                    nonfinite_run += 1
                    optimizer.zero_grad(set_to_none=True)
                    warnings.warn(f"non-finite loss or gradient at step {opt_steps + 1} (epoch {epoch + 1}, "
                                  f"samples {acc_idx} on rank {info.rank}): step skipped "
                                  f"({nonfinite_run} in a row)", RuntimeWarning, stacklevel=1)
                    logger.write({"kind": "nonfinite", "opt_step": opt_steps, "epoch": epoch + 1,
                                  "samples": acc_idx, "in_a_row": nonfinite_run})
                    if nonfinite_run >= cfg.max_nonfinite:
                        raise NonFiniteLossError(
                            f"{nonfinite_run} non-finite losses in a row (last at step {opt_steps + 1}, samples "
                            f"{acc_idx}); stopping. The last good checkpoint is {run.out / 'last.pt'} (lower "
                            "--lr or check the data)")
                else:
                    nonfinite_run = 0
                    optimizer.step()
                    optimizer.zero_grad(set_to_none=True)
                    if ema is not None:
                        ema.update(raw_model)
                    loss_sum += float(stats[0])
                    loss_n += n_global
                opt_steps += 1
                samples_seen += n_global
                samples_log += n_global
                step_loss = float(stats[0]) / max(1, n_global)
                elapsed = time.perf_counter() - t_log
                if run.progress:
                    bar.set_postfix(loss=f"{step_loss:.3f}", lr=f"{lr:.2e}",
                                    sps=f"{samples_log / max(elapsed, 1e-9):.2f}", refresh=False)
                if cfg.log_every and opt_steps % cfg.log_every == 0:
                    logger.write({"kind": "train", "opt_step": opt_steps, "epoch": epoch + 1,
                                  "samples_seen": samples_seen, "loss": step_loss, "lr": lr,
                                  "grad_norm": float(grad_norm),
                                  **{k: v / max(1, acc_n) for k, v in acc_terms.items()},
                                  "samples_per_s": samples_log / max(elapsed, 1e-9),
                                  "data_wait": wait_log / max(elapsed, 1e-9)})
                    t_log, wait_log, samples_log = time.perf_counter(), 0.0, 0
                micro_i, acc_loss, acc_terms, acc_n, acc_idx, acc_finite = 0, 0.0, {}, 0, [], True
                if (cfg.save_every_steps and opt_steps % cfg.save_every_steps == 0 and pos < per_epoch
                        and nonfinite_run == 0):  # never replace the last good checkpoint by a skipped step's
                    checkpoint(run.out / "last.pt")
            bar.close()
            del loader
            if pos != per_epoch:
                warnings.warn(f"epoch {epoch + 1}: the loader gave {pos} micro-batches, the plan said {per_epoch}",
                              RuntimeWarning, stacklevel=1)
            seconds = time.perf_counter() - t_epoch
            epoch += 1
            pos = 0
            rec = {"kind": "epoch", "opt_step": opt_steps, "epoch": epoch, "samples_seen": samples_seen,
                   "loss": loss_sum / max(1, loss_n), "seconds": seconds, "data_wait": wait_epoch / max(seconds, 1e-9),
                   "cpu_seconds": _cpu_seconds()}
            val = None
            if cfg.val_every and (epoch % cfg.val_every == 0 or epoch == cfg.epochs):
                val = _validate(run, raw_model, ema, say)
                if val:
                    rec.update({f"val_{k}": v for k, v in val.items()})
            logger.write(rec)
            say(f"epoch {epoch}: loss {rec['loss']:.4f}, {seconds:.0f} s, data wait {100 * rec['data_wait']:.1f}%"
                + (f", val mIoU {100 * val['miou']:.2f}%" if val and 'miou' in val else ""))
            score = None if not val else val.get("ema_miou", val.get("miou"))
            is_best = score is not None and not math.isnan(score) and (best is None or score > best)
            if is_best:
                best = score
            checkpoint(run.out / "last.pt", {"val": val})
            if info.is_main:
                if is_best:
                    _copy_atomic(run.out / "last.pt", run.out / "best.pt")
                if cfg.keep_epochs:
                    _copy_atomic(run.out / "last.pt", run.out / f"epoch_{epoch:03d}.pt")
                    for old in sorted(run.out.glob("epoch_*.pt"))[: -cfg.keep_epochs]:
                        old.unlink()
    except KeyboardInterrupt:
        interrupted = True
        if data is not None:
            data.close()  # stop the loader workers before saving and exiting
        # The position is the last optimizer-step boundary: the partial accumulation is redone on resume.
        if micro_i:
            pos -= micro_i
            optimizer.zero_grad(set_to_none=True)
        say(f"interrupted: saving {run.out / 'last.pt'} (epoch {epoch + 1}, micro-batch {pos}); "
            "continue with --resume")
        checkpoint(run.out / "last.pt")
    finally:
        logger.close()
    return TrainResult(out=run.out, epochs_done=epoch, opt_steps=opt_steps, best_miou=best, interrupted=interrupted)


def _copy_atomic(src: Path, dst: Path) -> None:
    tmp = dst.with_name(f".{dst.name}.tmp")
    try:
        with src.open("rb") as fi, tmp.open("wb") as fo:
            while chunk := fi.read(1 << 22):
                fo.write(chunk)
            fo.flush()
            os.fsync(fo.fileno())
        os.replace(tmp, dst)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OccDataError(f"could not write checkpoint {dst} ({exc.strerror or exc}); the previous one is "
                           "intact") from None


def _validate(run: _Run, raw_model: nn.Module, ema: EMA | None, say) -> dict[str, float] | None:
    """Val metrics with the shared evaluation: raw weights, and the EMA weights when kept ("ema_*").

    Every rank predicts its shard of the split; the accumulator states are summed across ranks."""
    fns = _evaluate_fns()
    if fns is None:
        say("validation skipped: fastocc.infer.evaluate is not available in this install")
        return None
    evaluate, all_reduce_report = fns
    from fastocc.infer.predict import PredictConfig

    pcfg = PredictConfig(store=run.cfg.store, split=run.cfg.val_split, batch_size=1, workers=run.cfg.workers,
                         device=str(run.info.device))
    temporal = raw_model.temporal
    queue_state = None if temporal is None else (temporal._feats, temporal._poses, temporal._bev_aug)

    def score() -> dict[str, float]:
        report = evaluate(raw_model, run.model_cfg, pcfg, rayiou=run.cfg.val_rayiou, progress=run.progress)
        return _report_dict(all_reduce_report(report, run.info.device) if run.info.enabled else report)

    out = score()
    if ema is not None:
        saved = {k: v.clone() for k, v in raw_model.state_dict().items()}
        raw_model.load_state_dict(ema.state)
        try:
            out.update({f"ema_{k}": v for k, v in score().items()})
        finally:
            raw_model.load_state_dict(saved)
    raw_model.clear_caches()  # evaluation reset the temporal queue; training continues with its own
    if queue_state is not None:
        temporal._feats, temporal._poses, temporal._bev_aug = queue_state
    raw_model.train()
    return out
