"""The training loop, readable top to bottom: `train` -> `run_epoch` -> `train_step`, `validate`, `end_epoch`.

Exact resume: a checkpoint is written only at optimizer-step boundaries and holds the whole `TrainState`
(weights, AdamW moments, EMA, progress -> learning rate, RNG states, temporal queue). The epoch's sample
order is a pure function of (seed, epoch) and the loader starts the epoch at batch k without decoding
the skipped samples (`skip_batches`). Stops: Ctrl-C (KeyboardInterrupt) and SIGTERM / the warning signal
(`preempt.StopRequest`, checked at every step boundary) both save `last.pt` at the last step boundary.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from fastocc import dist as D
from fastocc.checkpoint import rig_record
from fastocc.data.batch import Batch
from fastocc.data.dataset import StoreDataset, loader_batches
from fastocc.data.workers import start_iteration
from fastocc.losses import LossTargets, occupancy_loss
from fastocc.model.config import DepthBins, ModelConfig
from fastocc.train.config import TrainConfig, config_to_toml
from fastocc.train.preempt import StopRequest, stop_signals
from fastocc.train.runlock import RunLock
from fastocc.train.setup import (
    MetricsLog,
    Run,
    build_model,
    check_writable,
    estimate_step_seconds,
    init_from,
    loader_config,
    loss_config,
    make_run,
    new_state,
    pace_message,
    prepare_out,
    say_start,
    take_store_rig,
    take_val_split,
)
from fastocc.train.state import Progress, TrainState, get_rng_state
from occdata.errors import OccDataError
from occdata.fileio import copy_atomic, write_atomic

__all__ = ["NonFiniteLossError", "TrainResult", "depth_onehot", "run_epoch", "train", "train_step", "validate"]


class NonFiniteLossError(OccDataError):
    """Too many non-finite losses in a row; the last good checkpoint is kept."""


@dataclass(frozen=True)
class TrainResult:
    out: Path
    epochs_done: int
    opt_steps: int
    best_miou: float | None  # the selection score: EMA weights' val mIoU when kept, else the raw weights'
    interrupted: bool = False  # Ctrl-C
    preempted: str | None = None  # name of the stop signal (SIGTERM, SIGUSR1, ...) that ended the run
    is_main: bool = True  # rank 0 (the process that prints the summary)
    best_is_ema: bool = True
    steps_per_rank: tuple[int, ...] = ()  # optimizer steps of every process (a finished run; all equal)


def depth_onehot(depth: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Depth targets `(B, N, h, w)` metres (0 = none) -> one-hot bins `(B*N, D, h, w) float32`
    (all-zero where there is no target or the depth is outside [lower, upper))."""
    d = depth.flatten(0, 1)
    k = torch.floor((d - bins.lower) / bins.step).long()
    valid = (d > 0) & (k >= 0) & (k < bins.count)
    return (F.one_hot(k.clamp(0, bins.count - 1), bins.count) * valid[..., None]).permute(0, 3, 1, 2).float()


# -- one optimizer step ----------------------------------------------------------------------------------
def _targets(batch: Batch, model_cfg: ModelConfig) -> LossTargets:
    if not bool(batch.has_labels.all()):
        bad = batch.sample_index[~batch.has_labels].tolist()
        raise OccDataError(f"training samples {bad} have no labels; training needs a labelled split")
    return LossTargets(voxel_labels=batch.semantics, mask_camera=batch.mask_camera,
                       depth_onehot=depth_onehot(batch.depth_target, model_cfg.depth_bins),
                       bev_multihot=batch.bev_target)


def _micro_loss(run: Run, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Forward one micro-batch and return (total loss, terms): the one call site of the loss function."""
    with torch.autocast(device_type=run.info.device.type, dtype=torch.bfloat16, enabled=run.use_amp):
        out = run.model(batch.inputs())
    # occupancy_loss selects the camera-masked voxels once for all voxel terms (fastocc/losses.py)
    return occupancy_loss(out.voxel_logits.float(), _targets(batch, run.model_cfg), run.loss_cfg,
                          None if out.depth_probs is None else out.depth_probs.float(),
                          None if out.bev_logits is None else out.bev_logits.float())


@dataclass
class StepStats:
    """What one optimizer step did (summed over ranks where it says so)."""

    loss: float  # mean loss per sample, all ranks
    samples: int  # samples in the step, all ranks
    lr: float
    grad_norm: float
    terms: dict[str, float] = field(default_factory=dict)  # mean per sample, this rank
    skipped: bool = False  # non-finite loss or gradient somewhere: no update


def train_step(run: Run, state: TrainState, micro_batches: list[Batch]) -> StepStats:
    """Forward/backward each micro-batch (gradients accumulate; DDP syncs on the last), then one AdamW step
    (skipped on every rank when any rank saw a non-finite loss or gradient), EMA update, progress."""
    p, cfg, info = state.progress, run.cfg, run.info
    acc_loss, acc_n, acc_terms, finite, indices = 0.0, 0, {}, True, []
    for k, batch in enumerate(micro_batches):
        batch = batch.to(info.device, non_blocking=True)
        sync = run.model.no_sync if info.enabled and k < len(micro_batches) - 1 else contextlib.nullcontext
        with sync():
            total, terms = _micro_loss(run, batch)
            (total * (len(batch) / (run.micro * run.accum))).backward()
        finite &= bool(torch.isfinite(total))
        acc_loss += float(total.detach()) * len(batch)
        for name, v in terms.items():
            acc_terms[name] = acc_terms.get(name, 0.0) + float(v) * len(batch)
        acc_n += len(batch)
        indices += batch.sample_index.tolist()
    lr = cfg.lr_at(p.samples_seen, run.samples_per_epoch)
    for g in state.optimizer.param_groups:
        g["lr"] = lr
    grad_norm = nn.utils.clip_grad_norm_(state.model.parameters(), cfg.grad_clip) if cfg.grad_clip else torch.zeros(())
    ok = finite and bool(torch.isfinite(grad_norm))
    stats = D.all_reduce_sum(torch.tensor([acc_loss, float(acc_n), 0.0 if ok else 1.0], dtype=torch.float64), info)
    n_global, skipped = int(stats[1]), bool(stats[2] > 0)
    if skipped:
        state.optimizer.zero_grad(set_to_none=True)
        _non_finite(run, p, indices)
    else:
        p.nonfinite_run = 0
        state.optimizer.step()
        state.optimizer.zero_grad(set_to_none=True)
        if state.ema is not None:
            state.ema.update(state.model)
    p.opt_steps += 1
    p.samples_seen += n_global
    p.pos += len(micro_batches)
    return StepStats(loss=float(stats[0]) / max(1, n_global), samples=n_global, lr=lr, grad_norm=float(grad_norm),
                     terms={k: v / max(1, acc_n) for k, v in acc_terms.items()}, skipped=skipped)


def _non_finite(run: Run, p: Progress, indices: list[int]) -> None:
    p.nonfinite_run += 1
    warnings.warn(f"non-finite loss or gradient at step {p.opt_steps + 1} (epoch {p.epoch + 1}, samples {indices} on "
                  f"rank {run.info.rank}): step skipped ({p.nonfinite_run} in a row)", RuntimeWarning, stacklevel=2)
    run.logger.write({"kind": "nonfinite", "opt_step": p.opt_steps, "epoch": p.epoch + 1, "samples": indices,
                      "in_a_row": p.nonfinite_run})
    if p.nonfinite_run >= run.cfg.max_nonfinite:
        raise NonFiniteLossError(f"{p.nonfinite_run} non-finite losses in a row (last at step {p.opt_steps + 1}, "
                                 f"samples {indices}); stopping. The last good checkpoint is {run.out / 'last.pt'} "
                                 "(lower --lr or check the data)")


# -- one epoch -------------------------------------------------------------------------------------------
def _data_iter(loader) -> Iterator[tuple[Batch, float]]:
    """Batches with the seconds spent waiting for each.

    Ctrl-C is held back while the workers start (`start_iteration`). Closing the generator (Ctrl-C in
    the loop body, a stop signal) shuts the workers down at once.
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


def _step_groups(data: Iterator[tuple[Batch, float]], accum: int) -> Iterator[tuple[list[Batch], float]]:
    """Micro-batches grouped per optimizer step (`accum` each; the epoch's last group may be shorter)."""
    group, wait = [], 0.0
    for batch, w in data:
        group.append(batch)
        wait += w
        if len(group) == accum:
            yield group, wait
            group, wait = [], 0.0
    if group:
        yield group, wait


@dataclass
class _EpochLog:
    """Running sums for the epoch record and the periodic train records."""

    t_epoch: float = field(default_factory=time.perf_counter)
    wait_epoch: float = 0.0
    loss_sum: float = 0.0
    loss_n: int = 0
    t_log: float = field(default_factory=time.perf_counter)
    wait_log: float = 0.0
    samples_log: int = 0


def run_epoch(run: Run, state: TrainState) -> bool:
    """Train the rest of the current epoch from `progress.pos`; False when a stop signal ended it early
    (state at a step boundary, loader workers stopped)."""
    from tqdm import tqdm

    p, cfg = state.progress, run.cfg
    loader = run.epoch_loader(p.epoch, p.pos)
    per_epoch = loader_batches(loader)
    bar = tqdm(total=per_epoch, initial=p.pos, desc=f"epoch {p.epoch + 1}/{cfg.epochs}", dynamic_ncols=True,
               disable=not run.show_progress, unit="batch")
    run.model.train()
    log = _EpochLog()
    data = _data_iter(loader)
    steps_in_epoch = -(-(per_epoch - p.pos) // run.accum)
    run.pace.start_epoch()
    try:
        for group, wait in _step_groups(data, run.accum):
            log.wait_epoch += wait
            log.wait_log += wait
            step = train_step(run, state, group)
            bar.update(len(group))
            _log_step(run, state, step, log, bar)
            pace = run.pace.tick(steps_in_epoch)
            if pace is not None:
                run.say(pace_message(pace, min(run.pace.max_steps, steps_in_epoch - 1), -(-per_epoch // run.accum)))
            if run.stop.should_stop(run.info):
                return False
            if (cfg.save_every_steps and p.opt_steps % cfg.save_every_steps == 0 and p.pos < per_epoch
                    and p.nonfinite_run == 0):  # never replace the last good checkpoint by a skipped step's
                save_state(run, state)
    finally:
        data.close()  # stops the loader workers (also on Ctrl-C, before saving)
        bar.close()
    if p.pos != per_epoch:
        warnings.warn(f"epoch {p.epoch + 1}: the loader gave {p.pos} micro-batches, the plan said {per_epoch}",
                      RuntimeWarning, stacklevel=1)
    end_epoch(run, state, log)
    return True


def _log_step(run: Run, state: TrainState, step: StepStats, log: _EpochLog, bar: Any) -> None:
    p = state.progress
    if not step.skipped:
        log.loss_sum += step.loss * step.samples
        log.loss_n += step.samples
    log.samples_log += step.samples
    elapsed = max(time.perf_counter() - log.t_log, 1e-9)
    if run.show_progress:
        bar.set_postfix(loss=f"{step.loss:.3f}", lr=f"{step.lr:.2e}", sps=f"{log.samples_log / elapsed:.2f}",
                        refresh=False)
    if run.cfg.log_every and p.opt_steps % run.cfg.log_every == 0:
        run.logger.write({"kind": "train", "opt_step": p.opt_steps, "epoch": p.epoch + 1,
                          "samples_seen": p.samples_seen, "loss": step.loss, "lr": step.lr,
                          "grad_norm": step.grad_norm, **step.terms, "samples_per_s": log.samples_log / elapsed,
                          "data_wait": log.wait_log / elapsed})
        log.t_log, log.wait_log, log.samples_log = time.perf_counter(), 0.0, 0


def end_epoch(run: Run, state: TrainState, log: _EpochLog) -> None:
    """Epoch done: validate when due, log, say, keep best / epoch copies of last.pt."""
    p, cfg = state.progress, run.cfg
    seconds = time.perf_counter() - log.t_epoch
    p.epoch += 1
    p.pos = 0
    rec = {"kind": "epoch", "opt_step": p.opt_steps, "epoch": p.epoch, "samples_seen": p.samples_seen,
           "loss": log.loss_sum / max(1, log.loss_n), "seconds": seconds,
           "data_wait": log.wait_epoch / max(seconds, 1e-9), "cpu_seconds": _cpu_seconds()}
    val = None
    if cfg.val_every and (p.epoch % cfg.val_every == 0 or p.epoch == cfg.epochs):
        val = validate(run, state)
        if val:
            rec.update({f"val_{k}": v for k, v in val.items()})
    run.logger.write(rec)
    run.say(f"epoch {p.epoch}: loss {rec['loss']:.4f}, {seconds:.0f} s, data wait {100 * rec['data_wait']:.1f}%"
            + _val_text(val))
    score = None if not val else val.get("ema_miou", val.get("miou"))
    is_best = score is not None and not math.isnan(score) and (p.best_miou is None or score > p.best_miou)
    if is_best:
        p.best_miou = score
    save_state(run, state, {"val": val})
    if run.info.is_main:
        try:
            if is_best:
                copy_atomic(run.out / "last.pt", run.out / "best.pt")
            if cfg.keep_epochs:
                copy_atomic(run.out / "last.pt", run.out / f"epoch_{p.epoch:03d}.pt")
                for old in sorted(run.out.glob("epoch_*.pt"))[: -cfg.keep_epochs]:
                    old.unlink()
        except OSError as exc:
            raise OccDataError(f"could not copy checkpoint {run.out / 'last.pt'} ({exc.strerror or exc}); the "
                               "previous copies are intact") from None


def _val_text(val: dict[str, float] | None) -> str:
    """`, val mIoU raw 31.20% / EMA 30.10%`: which weights each figure is from, always said."""
    if not val or "miou" not in val:
        return ""
    text = f", val mIoU raw {100 * val['miou']:.2f}%"
    return text + (f" / EMA {100 * val['ema_miou']:.2f}%" if "ema_miou" in val else "")


def _cpu_seconds() -> float:
    """CPU time of this process and its finished children (loader workers of past epochs)."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


# -- validation ------------------------------------------------------------------------------------------
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


def validate(run: Run, state: TrainState) -> dict[str, float] | None:
    """Val metrics with the shared evaluation: raw weights, and the EMA weights when kept ("ema_*").

    Every rank predicts its shard of the split; the accumulator states are summed across ranks. The
    training temporal queue is set aside and restored (evaluation runs its own sequences)."""
    fns = _evaluate_fns()
    if fns is None:
        run.say("validation skipped: fastocc.infer.evaluate is not available in this install")
        return None
    evaluate, all_reduce_report = fns
    from fastocc.infer.predict import PredictConfig

    model, info = state.model, run.info
    pcfg = PredictConfig(store=run.cfg.store, split=run.cfg.val_split, batch_size=1, workers=run.cfg.workers,
                         device=str(info.device))
    queue = None if model.temporal is None else model.temporal.queue_state()

    def score() -> dict[str, float]:
        report = evaluate(model, run.model_cfg, pcfg, rayiou=run.cfg.val_rayiou, progress=run.show_progress)
        return _report_dict(all_reduce_report(report, info.device) if info.enabled else report)

    out = score()
    if state.ema is not None:
        saved = {k: v.clone() for k, v in model.state_dict().items()}
        model.load_state_dict(state.ema.state)
        try:
            out.update({f"ema_{k}": v for k, v in score().items()})
        finally:
            model.load_state_dict(saved)
    model.clear_caches()
    if model.temporal is not None:
        model.temporal.load_queue_state(queue)
    model.train()
    return out


# -- saving ----------------------------------------------------------------------------------------------
def save_state(run: Run, state: TrainState, meta_extra: dict[str, Any] | None = None) -> None:
    """Write `last.pt` (rank 0) from the state at a step boundary; every rank contributes its RNG state."""
    rng = [get_rng_state()]
    if run.info.enabled:
        gathered: list[Any] = [None] * run.info.world_size
        torch.distributed.all_gather_object(gathered, rng[0])
        rng = gathered
    if not run.info.is_main:
        return
    p = state.progress
    meta = {"epoch": p.epoch, "opt_steps": p.opt_steps, "samples_seen": p.samples_seen, **(meta_extra or {})}
    path = run.out / "last.pt"
    try:
        state.save(path, run.model_cfg, rng, meta, run.cfg.to_dict(), rig_record(run.cameras))
    except OSError as exc:
        raise OccDataError(f"could not write checkpoint {path} ({exc.strerror or exc}); the previous "
                           "checkpoint there is intact") from None


# -- the driver ------------------------------------------------------------------------------------------
def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> TrainResult:
    """Train (or continue with `resume`) as described by `cfg`; returns when done, interrupted (Ctrl-C) or
    preempted (SIGTERM / the warning signal): the last two after writing `last.pt`.

    Under torchrun each process calls this; rank 0 holds the run folder's lock and writes it."""
    if resume and cfg.init_from:
        raise OccDataError("--init-from starts a new run; it cannot be combined with --resume")
    info = D.setup(cfg.device, cfg.dist_timeout)
    try:
        with D.collective_errors(info), StopRequest(stop_signals(cfg.warn_signal)) as stop:
            if not info.is_main:
                return _train(cfg, info, resume, progress, stop)
            check_writable(Path(cfg.out))
            with RunLock(cfg.out):
                return _train(cfg, info, resume, progress, stop)
    finally:
        D.teardown(info)


# A test hook: a FIFO read once the stop signals are handled (and, on rank 0, the run folder locked),
# before any set-up work, so a test's signal lands before the first step on any machine.
TEST_GATE_ENV = "FASTOCC_TEST_GATE"


def _train(cfg: TrainConfig, info: D.DistInfo, resume: bool, progress: bool, stop: StopRequest) -> TrainResult:
    if os.environ.get(TEST_GATE_ENV):
        Path(os.environ[TEST_GATE_ENV]).read_bytes()  # returns when the test closes its end
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.deterministic:
        torch.use_deterministic_algorithms(True)
    run = make_run(cfg, info, progress, stop)
    split_note = take_val_split(run)
    cfg = run.cfg  # the resolved validation split is the one recorded
    payload = prepare_out(run, resume)
    take_store_rig(run, payload)
    if info.is_main:
        write_atomic(run.out / "config.toml", config_to_toml(cfg).encode())
        write_atomic(run.out / "config.json", (json.dumps(cfg.to_dict(), indent=2) + "\n").encode())
    state = new_state(run, build_model(run))
    run.loss_cfg = loss_config(run)
    run.loader_cfg = loader_config(run)
    probe = StoreDataset(run.loader_cfg)
    run.samples_per_epoch = len(probe)
    if run.samples_per_epoch == 0:
        raise OccDataError(f"no built samples in the {cfg.train_split!r} split of {cfg.store}")
    say_start(run)
    if split_note:
        run.say(split_note)
    if payload is not None:
        state.load_state_dict(payload, info.rank, run.out / "last.pt")
        p = state.progress
        run.say(f"resuming {run.out / 'last.pt'}: epoch {p.epoch + 1} at micro-batch {p.pos}, {p.opt_steps} steps done")
    elif cfg.init_from:
        init_from(state, cfg.init_from)
        run.say(f"initialised from {cfg.init_from} (model{'' if state.ema is None else ' and EMA'} weights)")
    run.logger = MetricsLog(run.out, info.is_main, state.progress.opt_steps if payload is not None else None)
    probe.set_epoch(state.progress.epoch)
    per_epoch = probe.num_batches(cfg.workers)
    if info.device.type == "cpu" and info.is_main:
        dt = estimate_step_seconds(run, state.model)
        run.say(f"estimated time per epoch on CPU: ~{dt * per_epoch / 60:.1f} min ({per_epoch} micro-batches x "
                f"{dt:.2f} s forward+backward, one synthetic batch after a warm-up pass; data loading not included; "
                "the measured pace follows after the first steps)")
    D.barrier(info)
    run.model = state.model
    if info.enabled:  # wrap after the time estimate: DDP's gradient hooks must see only real steps
        run.model = nn.parallel.DistributedDataParallel(
            state.model, device_ids=[info.device.index] if info.device.type == "cuda" else None,
            find_unused_parameters=True)  # e.g. the ResNet fc layer is never used
    try:
        return _loop(run, state)
    finally:
        run.logger.close()


def _loop(run: Run, state: TrainState) -> TrainResult:
    """Epochs until done; Ctrl-C or a stop signal saves `last.pt` at the last step boundary."""
    p = state.progress
    result = dict(out=run.out, is_main=run.info.is_main, best_is_ema=state.ema is not None)
    try:
        while p.epoch < run.cfg.epochs:
            if run.stop.should_stop(run.info) or not run_epoch(run, state):
                name = run.stop.received.name if run.stop.received is not None else "a stop signal on another rank"
                run.say(f"{name}: saving {run.out / 'last.pt'} (epoch {p.epoch + 1}, micro-batch {p.pos}, "
                        f"{p.opt_steps} steps); continue with --resume")
                save_state(run, state)
                return TrainResult(epochs_done=p.epoch, opt_steps=p.opt_steps, best_miou=p.best_miou,
                                   preempted=name, **result)
    except KeyboardInterrupt:
        state.optimizer.zero_grad(set_to_none=True)  # a partial accumulation is redone on resume
        run.say(f"interrupted: saving {run.out / 'last.pt'} (epoch {p.epoch + 1}, micro-batch {p.pos}); "
                "continue with --resume")
        save_state(run, state)
        return TrainResult(epochs_done=p.epoch, opt_steps=p.opt_steps, best_miou=p.best_miou, interrupted=True,
                           **result)
    # every rank ran the same number of steps (DDP needs it; order.py plans it): reported by rank 0
    steps = D.gather_ints(p.opt_steps, run.info)
    return TrainResult(epochs_done=p.epoch, opt_steps=p.opt_steps, best_miou=p.best_miou, steps_per_rank=steps,
                       **result)
