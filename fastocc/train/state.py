"""Training state that must survive a restart, as one object: `TrainState` (saved and loaded symmetrically).

A training checkpoint is a `fastocc.checkpoint` file (so `fastocc eval/predict` read it with no flags)
with extra keys for exact resume: optimizer, progress (samples seen -> the schedule, epoch and
micro-batch position, best score, non-finite streak), RNG states of every rank, the temporal queue
and the resolved train config.
"""

from __future__ import annotations

import dataclasses
import json
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from fastocc.checkpoint import CheckpointError, load_checkpoint, load_weights, save_checkpoint
from fastocc.model.config import ModelConfig
from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.errors import OccDataError
from occdata.fileio import write_atomic
from occdata.store.reader import open_store

__all__ = ["EMA", "Progress", "TrainState", "class_counts", "get_rng_state", "load_resume", "set_rng_state"]


class EMA:
    """Exponential moving average of the weights (floating tensors; integer buffers are copied).

    decay_n = min(decay, (1 + n) / (10 + n)) at update n, so early averages are not dominated by the
    random initialisation."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        self.decay = decay
        self.updates = 0
        self.state = {k: v.detach().clone() for k, v in model.state_dict().items()}

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for k, v in model.state_dict().items():
            ema = self.state[k]
            if ema.dtype.is_floating_point:
                ema.mul_(d).add_(v.detach(), alpha=1 - d)
            else:
                ema.copy_(v)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The averaged weights on the CPU."""
        return {k: v.cpu() for k, v in self.state.items()}

    def load_state_dict(self, state: dict[str, torch.Tensor], updates: int) -> None:
        device = next(iter(self.state.values())).device
        self.state = {k: v.to(device) for k, v in state.items()}
        self.updates = int(updates)


def get_rng_state() -> dict[str, Any]:
    """Python, numpy and torch (CPU, CUDA) generator states as tensors/primitives (weights_only-safe)."""
    py = random.getstate()
    np_state = np.random.get_state()  # noqa: NPY002 - the legacy global generator third-party code may use
    state = {
        "python": [py[0], list(py[1]), py[2]],
        "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), int(np_state[2]), int(np_state[3]),
                  float(np_state[4])],
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    n = state["numpy"]
    np.random.set_state((n[0], n[1].numpy().astype(np.uint32), n[2], n[3], n[4]))  # noqa: NPY002
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def class_counts(store: str | Path, split: str, use_camera_mask: bool, cache: Path | None = None) -> np.ndarray:
    """Voxel count per class `(18,) int64` over the training split (inside the camera mask when the
    losses use it). Computed once and cached as JSON in the run folder (`cache`)."""
    if cache is not None and cache.is_file():
        saved = json.loads(cache.read_text())
        if saved.get("split") == split and saved.get("camera_mask") == use_camera_mask:
            return np.asarray(saved["counts"], dtype=np.int64)
    reader = open_store(store)
    idx = reader.split_indices(split)
    if not len(idx):
        counts = {s: len(reader.split_indices(s)) for s in reader.attrs.get("splits", [])}
        raise OccDataError(f"the store has no built samples in the {split!r} split (its splits: {counts}); set "
                           "train_split in a --config TOML, or rebuild with occdata build --split-file FILE")
    unlabelled = reader.split_indices(split, labelled=False)
    if len(unlabelled):
        raise OccDataError(f"{len(unlabelled)} sample(s) of the training split {split!r} have no labels "
                           f"(e.g. {reader.token(int(unlabelled[0]))}); training needs Occ3D labels (--gts)")
    sem, cam = reader.array("labels/semantics"), reader.array("labels/mask_camera")
    counts = np.zeros(NUM_CLASSES, dtype=np.int64)
    block = int(sem.chunks[0])
    for lo in range(int(idx[0]) // block * block, int(idx[-1]) + 1, block):  # one read per chunk
        mine = idx[(idx >= lo) & (idx < lo + block)]
        if not len(mine):
            continue
        s = np.asarray(sem[lo: lo + block])[mine - lo]
        if use_camera_mask:
            s = s[np.asarray(cam[lo: lo + block])[mine - lo].astype(bool)]
        counts += np.bincount(s.reshape(-1), minlength=NUM_CLASSES)[:NUM_CLASSES]
    if cache is not None:
        write_atomic(cache, json.dumps({"split": split, "camera_mask": use_camera_mask, "counts": counts.tolist(),
                                        "free_label": FREE_LABEL}).encode())
    return counts


@dataclass
class Progress:
    """Where the run is: epoch (0-based, the one in progress), micro-batches of it done (always at an
    optimizer-step boundary), samples seen (-> learning rate), optimizer steps, best val score and the
    current run of non-finite steps."""

    epoch: int = 0
    pos: int = 0
    samples_seen: int = 0
    opt_steps: int = 0
    best_miou: float | None = None
    nonfinite_run: int = 0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Progress:
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


@dataclass
class TrainState:
    """Everything the next optimizer step depends on: weights, AdamW moments, EMA, progress, RNG, queue.

    `state_dict` / `load_state_dict` are exact inverses; `model` is the raw network (not the DDP wrapper)."""

    model: nn.Module
    optimizer: torch.optim.Optimizer
    ema: EMA | None
    progress: Progress = field(default_factory=Progress)

    def state_dict(self, rng: list[dict[str, Any]]) -> dict[str, Any]:
        """The checkpoint keys of this state; `rng` holds every rank's `get_rng_state()` (rank order)."""
        temporal = getattr(self.model, "temporal", None)
        return {
            "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
            "ema": None if self.ema is None else self.ema.state_dict(),
            "ema_updates": 0 if self.ema is None else self.ema.updates,
            "optimizer": self.optimizer.state_dict(),
            "progress": dataclasses.asdict(self.progress),
            "rng": rng,
            "temporal_queue": None if temporal is None else temporal.queue_state(),
        }

    def load_state_dict(self, payload: dict[str, Any], rank: int, source: str | Path = "checkpoint") -> None:
        """Restore from `state_dict`'s keys (a loaded checkpoint payload) for this `rank`."""
        load_weights(self.model, payload["model"], source)
        self.optimizer.load_state_dict(payload["optimizer"])
        if self.ema is not None:
            if payload.get("ema") is None:
                raise OccDataError("--resume: the checkpoint has no EMA weights but ema = true")
            self.ema.load_state_dict(payload["ema"], payload["ema_updates"])
        self.progress = Progress.from_dict(payload["progress"])
        rng = payload["rng"]
        set_rng_state(rng[rank] if rank < len(rng) else rng[0])
        temporal = getattr(self.model, "temporal", None)
        if temporal is not None:
            temporal.load_queue_state(payload.get("temporal_queue"))

    def save(self, path: Path, model_cfg: ModelConfig, rng: list[dict[str, Any]], meta: dict[str, Any],
             train_config: dict[str, Any], rig: dict[str, Any] | None = None) -> Path:
        """Write a training checkpoint atomically (the previous file at `path` survives any failure); `rig`:
        `fastocc.checkpoint.rig_record` of the store's cameras (empty for nuScenes')."""
        sd = self.state_dict(rng)
        return save_checkpoint(path, model_cfg, sd.pop("model"), sd.pop("ema"), meta=meta, train_config=train_config,
                               **(rig or {}), **sd)


def load_resume(path: Path) -> dict[str, Any]:
    """The payload of a training checkpoint, checked to carry the resume keys."""
    ckpt = load_checkpoint(path)
    missing = [k for k in ("optimizer", "train_config", "progress", "rng") if k not in ckpt.payload]
    if missing:
        raise CheckpointError(f"{path}: not a training checkpoint (missing {missing}); cannot resume from it")
    return ckpt.payload
