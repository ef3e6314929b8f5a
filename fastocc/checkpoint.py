"""Checkpoints that carry their model config: atomic writes, `torch.load(weights_only=True)` reads.

One format serves the trainer (resume), `fastocc predict/eval` (no preset flags) and `fastocc export`.
A checkpoint is a plain dict of tensors and primitives:

    format            "fastocc.checkpoint"
    version           1
    model_config      JSON text of the ModelConfig (`model_config_to_dict`)
    model             state dict of the raw weights
    ema               state dict of the EMA weights, or None
    meta              dict of primitives (epoch, step, val metrics, ...) for people and tools
    rig               {"cameras": [...]}: the camera order trained on, only for a rig other than nuScenes'
                      (absent: nuScenes' 6 cameras, so those checkpoints are as before; `checkpoint_cameras`)
    ...               any further keys the trainer needs to resume (optimizer, scheduler, RNG states)
"""

from __future__ import annotations

import dataclasses
import json
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from fastocc.model.config import (
    BackboneConfig,
    BevHeight,
    DepthBins,
    HeadKind,
    ModelConfig,
    TemporalFusionKind,
    ViewTransformKind,
)
from occdata.constants import CAMERA_ORDER, OccGrid
from occdata.errors import OccDataError
from occdata.fileio import atomic_open

__all__ = [
    "CHECKPOINT_FORMAT",
    "Checkpoint",
    "CheckpointError",
    "check_checkpoint_file",
    "checkpoint_cameras",
    "first_mismatch",
    "load_checkpoint",
    "load_model",
    "load_weights",
    "model_config_from_dict",
    "model_config_to_dict",
    "newest_epoch_checkpoint",
    "rig_record",
    "save_checkpoint",
]

CHECKPOINT_FORMAT = "fastocc.checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(OccDataError):
    """A file that is not a readable fastocc checkpoint (the CLI prints it as one line)."""


def model_config_to_dict(cfg: ModelConfig) -> dict[str, Any]:
    """A JSON-able dict of primitives; `model_config_from_dict` inverts it exactly."""
    d = dataclasses.asdict(cfg)
    for k in ("head", "bev_height", "temporal_fusion", "view_transform"):
        d[k] = str(getattr(cfg, k))
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
        "bev_height": BevHeight,
        "temporal_fusion": TemporalFusionKind,
        "view_transform": ViewTransformKind,
        "fine_grid": grid,
        "coarse_grid": grid,
        "depth_bins": lambda v: DepthBins(**v),
    }
    return ModelConfig(**{k: conv[k](v) if k in conv else v for k, v in d.items()})


def rig_record(cameras: tuple[str, ...]) -> dict[str, Any]:
    """The checkpoint keys that record the camera order `cameras` trained on: `{"rig": ...}`, or none for
    nuScenes' own order (a nuScenes checkpoint stays what it was before rigs were recorded)."""
    return {} if tuple(cameras) == CAMERA_ORDER else {"rig": {"cameras": list(cameras)}}


def checkpoint_cameras(payload: dict[str, Any], num_cams: int) -> tuple[str, ...] | None:
    """The camera order a checkpoint payload was trained on: its `rig` record; nuScenes' order for a
    6-camera checkpoint without one (every checkpoint before rigs were recorded); None (unknown) for
    other camera counts without one (e.g. a network saved outside the trainer)."""
    rig = payload.get("rig")
    if isinstance(rig, dict) and isinstance(rig.get("cameras"), list | tuple):
        return tuple(str(c) for c in rig["cameras"])
    return CAMERA_ORDER if num_cams == len(CAMERA_ORDER) else None


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint. `payload` holds every key as saved (for resume)."""

    model_config: ModelConfig
    model: dict[str, torch.Tensor]
    ema: dict[str, torch.Tensor] | None
    meta: dict[str, Any]
    payload: dict[str, Any]

    @property
    def cameras(self) -> tuple[str, ...] | None:
        """The camera order trained on (`checkpoint_cameras`); None when unknown."""
        return checkpoint_cameras(self.payload, self.model_config.num_cams)

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
    """Write atomically (`occdata.fileio.atomic_open`: temporary file, fsync, rename; the umask's mode).

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
    try:
        with atomic_open(path) as f:
            torch.save(payload, f)
    except RuntimeError as exc:
        # torch's zip writer turns a failed write of the file (a full disk: OSError ENOSPC) into a RuntimeError
        # ("enforce fail at inline_container.cc", "file write failed"); give callers the OSError back.
        cause = _os_error_in(exc)
        if cause is None:
            raise
        raise cause from None
    return path


def _os_error_in(exc: BaseException) -> OSError | None:
    """The OSError among an exception's causes and contexts (what a failed write raised), or None."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, OSError):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def newest_epoch_checkpoint(folder: str | Path, exclude: Path | None = None) -> Path | None:
    """The `epoch_NNN.pt` with the highest N in `folder` (the trainer keeps the last few), or None."""
    found = sorted((int(m.group(1)), p) for p in Path(folder).glob("epoch_*.pt")
                   if (m := re.fullmatch(r"epoch_(\d+)\.pt", p.name)) and p != exclude)
    return found[-1][1] if found else None


def _why_unreadable(path: Path) -> str:
    """What is wrong with a file torch cannot load with weights_only=True, in a few words (never torch's
    advice to load with weights_only=False: that would run code from the file)."""
    size = path.stat().st_size
    if size == 0:
        return "truncated (an empty file)"
    with path.open("rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":
        return "not a checkpoint at all (not a torch file)"
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError, EOFError):
        return f"truncated or damaged ({size} bytes; the archive does not read to its end)"
    if bad is not None:
        return f"damaged (member {bad} fails its checksum)"
    return "it holds Python objects besides tensors (refused: loading them could run code)"


def _unreadable(path: Path, why: str) -> CheckpointError:
    newest = newest_epoch_checkpoint(path.parent, exclude=path)
    hint = f"; the newest epoch checkpoint there is {newest}" if newest is not None else ""
    return CheckpointError(f"{path}: {why}{hint}")


def check_checkpoint_file(path: str | Path) -> Path:
    """`path` when it is a file; else one `CheckpointError` line (checked before anything slower or
    anything about the store, so that a mistyped path is the first thing said)."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: is a folder, not a checkpoint file (e.g. {path / 'best.pt'})")
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read a checkpoint with `torch.load(weights_only=True)` (never unpickles code).

    A file that cannot be used is one `CheckpointError` line naming it: truncated, not a checkpoint or
    from another version, pointing to the newest `epoch_NNN.pt` beside it when there is one."""
    path = check_checkpoint_file(path)
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception:  # a truncated file, a pickle with code, not a torch file at all
        raise _unreadable(path, f"not a readable fastocc checkpoint: {_why_unreadable(path)}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        hint = " (it looks like a bare state dict: use --pretrained for backbone weights)" if isinstance(
            payload, dict) and payload and all(isinstance(v, torch.Tensor) for v in payload.values()) else ""
        raise _unreadable(path, f"not a fastocc checkpoint{hint}")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise _unreadable(path, f"checkpoint version {payload.get('version')} is from another fastocc version "
                                f"(this one reads version {CHECKPOINT_VERSION})")
    try:
        cfg = model_config_from_dict(json.loads(payload["model_config"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise _unreadable(path, f"bad model config in checkpoint ({exc})") from None
    cams = checkpoint_cameras(payload, cfg.num_cams)
    if cams is not None and len(cams) != cfg.num_cams:
        raise _unreadable(path, f"its rig names {len(cams)} cameras but its model config has {cfg.num_cams}")
    return Checkpoint(model_config=cfg, model=payload["model"], ema=payload.get("ema"),
                      meta=dict(payload.get("meta") or {}), payload=payload)


def first_mismatch(expected: dict[str, torch.Tensor], given: dict[str, torch.Tensor]) -> str | None:
    """The first key (in the model's order) whose tensor is missing, extra or of another shape, described
    as "key 'k': checkpoint (a, b), model (c, d)"; None when every key and shape fits."""
    for k, v in expected.items():
        if k not in given:
            return f"key {k!r}: not in the checkpoint, model {tuple(v.shape)}"
        if tuple(given[k].shape) != tuple(v.shape):
            return f"key {k!r}: checkpoint {tuple(given[k].shape)}, model {tuple(v.shape)}"
    extra = [k for k in given if k not in expected]
    if extra:
        return f"key {extra[0]!r}: checkpoint {tuple(given[extra[0]].shape)}, not in the model"
    return None


def load_weights(model: torch.nn.Module, state: dict[str, torch.Tensor], source: str | Path) -> None:
    """`model.load_state_dict(state)`, or one `CheckpointError` naming the first differing key and shapes."""
    bad = first_mismatch(model.state_dict(), state)
    if bad is not None:
        raise CheckpointError(f"{source}: weights do not fit the model config (first difference at {bad})")
    model.load_state_dict(state)


def load_model(
    path: str | Path, device: str | torch.device = "cpu", prefer_ema: bool = True
) -> tuple[torch.nn.Module, Checkpoint]:
    """Build the network from a checkpoint's own config, load its weights, eval mode, on `device`."""
    from fastocc.model import FastOcc

    ckpt = load_checkpoint(path)
    model = FastOcc(ckpt.model_config)
    load_weights(model, ckpt.weights(prefer_ema), path)
    return model.to(device).eval(), ckpt
