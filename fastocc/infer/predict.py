"""Run a network over a store split in scene order, optionally with BEV-flip test-time augmentation.

The images go through the loader's test transform (`fastocc.data`: resize, bottom crop, normalise), so
predictions see exactly what validation during training sees.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader
from fastocc.data.batch import Batch
from fastocc.data.workers import start_iteration
from fastocc.model.config import ModelConfig
from fastocc.model.inputs import SceneInputs

__all__ = ["PredictConfig", "bev_flip_variants", "predict_split"]

# (flip_x, flip_y) of the four TTA variants; (False, False) is the plain forward pass.
_FLIPS: tuple[tuple[bool, bool], ...] = ((False, False), (True, False), (False, True), (True, True))


@dataclass(frozen=True)
class PredictConfig:
    """What to predict. `split` None = every built sample; `tta` averages the class probabilities of the
    four BEV flips (none, x, y, both), each un-flipped exactly (flips need no resampling)."""

    store: str | Path
    split: str | None = "val"
    batch_size: int = 1
    workers: int = 0
    tta: bool = False
    device: str = "cpu"


def bev_flip_variants(inputs: SceneInputs) -> list[tuple[tuple[bool, bool], SceneInputs]]:
    """The four TTA inputs: M replaced by flip @ M for each (flip_x, flip_y)."""
    out = []
    for fx, fy in _FLIPS:
        F = torch.diag(torch.tensor([-1.0 if fx else 1.0, -1.0 if fy else 1.0, 1.0, 1.0])).to(inputs.bev_aug)
        out.append(((fx, fy), SceneInputs(**{**inputs.__dict__, "bev_aug": F @ inputs.bev_aug})))
    return out


def _unflip(t: Tensor, fx: bool, fy: bool) -> Tensor:
    """Undo a BEV flip on `(B, C, X, Y, Z)`: a flip of the frame is a reversal of the grid axis."""
    dims = [d for d, f in ((2, fx), (3, fy)) if f]
    return t.flip(dims) if dims else t


def _sample_config(model_cfg: ModelConfig) -> SampleConfig:
    H, W = model_cfg.input_hw
    return SampleConfig(image=ImageAugConfig(height=H, width=W, train=False), bev=BevAugConfig(train=False))


@torch.no_grad()
def predict_split(
    model: nn.Module, model_cfg: ModelConfig, cfg: PredictConfig, rank: int | None = None,
    world_size: int | None = None,
) -> Iterator[tuple[Batch, Tensor]]:
    """Yield `(batch, probs)` over the split: batch on CPU (test transform, labels as stored), probs
    `(B, 18, 200, 200, 16) float32` softmax class probabilities on CPU.

    Scene-sequential order, so temporal models carry their queue (reset at each sequence start); with
    `tta` each flip variant keeps its own queue. `rank`/`world_size` shard the split (None: from
    torch.distributed when initialised).
    """
    device = torch.device(cfg.device)
    loader = make_loader(
        LoaderConfig(store=cfg.store, batch_size=cfg.batch_size, sequential=True, sample=_sample_config(model_cfg),
                     splits=(cfg.split,) if cfg.split else (), rank=rank, world_size=world_size),
        num_workers=cfg.workers,
    )
    loader.dataset.set_epoch(0)
    was_training = model.training
    model.eval()
    # Temporal state lives in the module; each TTA variant needs its own copy of it.
    n_variants = len(_FLIPS) if cfg.tta else 1
    models = [model] + [copy.deepcopy(model) for _ in range(n_variants - 1)]
    for m in models:
        m.clear_caches()
    try:
        for batch in start_iteration(loader):  # a Ctrl-C while workers start: no worker tracebacks
            inputs = batch.inputs().to(device)
            variants = bev_flip_variants(inputs) if cfg.tta else [((False, False), inputs)]
            probs = None
            for m, ((fx, fy), inp) in zip(models, variants, strict=True):
                p = _unflip(torch.softmax(m(inp).voxel_logits.float(), dim=1), fx, fy)
                probs = p if probs is None else probs + p
            yield batch, (probs / len(variants)).cpu()
    finally:
        model.train(was_training)
