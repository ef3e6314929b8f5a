"""Checkpoints that carry their model config: atomic writes, `torch.load(weights_only=True)` reads.

One format serves the trainer (resume), `fastocc predict/eval` (no preset flags) and `fastocc export`.
A checkpoint is a plain dict of tensors and primitives:

    format            "fastocc.checkpoint"
    version           1
    model_config      JSON text of the ModelConfig (`model_config_to_dict`)
    model             state dict of the raw weights
    ema               state dict of the EMA weights, or None
    meta              dict of primitives (epoch, step, val metrics, ...) for people and tools
    ...               any further keys the trainer needs to resume (optimizer, scheduler, RNG states)
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from fastocc.model.config import BackboneConfig, DepthBins, HeadKind, ModelConfig
from occdata.constants import OccGrid
from occdata.errors import OccDataError

__all__ = [
    "CHECKPOINT_FORMAT",
    "Checkpoint",
    "CheckpointError",
    "load_checkpoint",
    "load_model",
    "model_config_from_dict",
    "model_config_to_dict",
    "save_checkpoint",
]

CHECKPOINT_FORMAT = "fastocc.checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(OccDataError):
    """A file that is not a readable fastocc checkpoint (the CLI prints it as one line)."""


def model_config_to_dict(cfg: ModelConfig) -> dict[str, Any]:
    """A JSON-able dict of primitives; `model_config_from_dict` inverts it exactly."""
    d = dataclasses.asdict(cfg)
    d["head"] = str(cfg.head)
    return json.loads(json.dumps(d))  # tuples -> lists, checks it is JSON-able


def model_config_from_dict(d: dict[str, Any]) -> ModelConfig:
    """Inverse of `model_config_to_dict`; unknown keys are an error naming them."""
    d = dict(d)
    known = {f.name for f in dataclasses.fields(ModelConfig)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise CheckpointError(f"model config has unknown keys {unknown}")

    def grid(g: dict[str, Any]) -> OccGrid:
        return OccGrid(lower=tuple(g["lower"]), upper=tuple(g["upper"]), voxel_size=float(g["voxel_size"]))

    conv = {
        "backbone": lambda v: BackboneConfig(**v),
        "input_hw": lambda v: (int(v[0]), int(v[1])),
        "head": HeadKind,
        "fine_grid": grid,
        "coarse_grid": grid,
        "depth_bins": lambda v: DepthBins(**v),
    }
    return ModelConfig(**{k: conv[k](v) if k in conv else v for k, v in d.items()})


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint. `payload` holds every key as saved (for resume)."""

    model_config: ModelConfig
    model: dict[str, torch.Tensor]
    ema: dict[str, torch.Tensor] | None
    meta: dict[str, Any]
    payload: dict[str, Any]

    def weights(self, prefer_ema: bool = True) -> dict[str, torch.Tensor]:
        """The EMA weights when present and preferred (what evaluation uses), else the raw ones."""
        return self.ema if prefer_ema and self.ema is not None else self.model


def save_checkpoint(
    path: str | Path,
    model_config: ModelConfig,
    model_state: dict[str, torch.Tensor],
    ema_state: dict[str, torch.Tensor] | None = None,
    meta: dict[str, Any] | None = None,
    **extra: Any,
) -> Path:
    """Write atomically: a temporary file in the same folder, fsync, then rename over `path`.

    A crash or a full disk while writing leaves any previous file at `path` intact (the temporary file
    is removed and the error re-raised)."""
    path = Path(path)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "model_config": json.dumps(model_config_to_dict(model_config)),
        "model": model_state,
        "ema": ema_state,
        "meta": dict(meta or {}),
        **extra,
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read a checkpoint with `torch.load(weights_only=True)` (never unpickles code)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # a truncated file, a pickle with code, not a torch file at all
        raise CheckpointError(f"{path}: not a readable fastocc checkpoint ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        hint = " (it looks like a bare state dict: use --pretrained for backbone weights)" if isinstance(
            payload, dict) and payload and all(isinstance(v, torch.Tensor) for v in payload.values()) else ""
        raise CheckpointError(f"{path}: not a fastocc checkpoint{hint}")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {payload.get('version')} is not supported "
                              f"(this fastocc reads version {CHECKPOINT_VERSION})")
    try:
        cfg = model_config_from_dict(json.loads(payload["model_config"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: bad model config in checkpoint ({exc})") from None
    return Checkpoint(model_config=cfg, model=payload["model"], ema=payload.get("ema"),
                      meta=dict(payload.get("meta") or {}), payload=payload)


def load_model(
    path: str | Path, device: str | torch.device = "cpu", prefer_ema: bool = True
) -> tuple[torch.nn.Module, Checkpoint]:
    """Build the network from a checkpoint's own config, load its weights, eval mode, on `device`."""
    from fastocc.model import FastOcc

    ckpt = load_checkpoint(path)
    model = FastOcc(ckpt.model_config)
    try:
        model.load_state_dict(ckpt.weights(prefer_ema))
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not fit the model config ({str(exc).splitlines()[0]})") from None
    return model.to(device).eval(), ckpt
