"""`TrainConfig`: every knob of a training run, frozen; read from TOML, overridden by CLI options.

Precedence: dataclass defaults < TOML file (`[train]` table or top level) < command-line options.
The resolved config is written to the run folder as `config.toml` and `config.json`; `--resume` checks
that the stored one is compatible (same model, data and schedule) and names the fields that differ.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastocc.model.config import (
    PRESETS,
    BevHeight,
    HeadKind,
    ModelConfig,
    TemporalFusionKind,
    ViewTransformKind,
    preset,
)
from occdata.errors import OccDataError

__all__ = [
    "RESUME_MAY_CHANGE",
    "WARN_SIGNALS",
    "ConfigError",
    "LossWeights",
    "TrainConfig",
    "config_from_dict",
    "config_to_toml",
    "incompatible_fields",
    "load_config",
]


class ConfigError(OccDataError):
    """A bad training config (unknown key, wrong type, bad value); printed as one line by the CLI."""


WARN_SIGNALS = ("USR1", "USR2", "none")  # the warning signal a scheduler may send before SIGTERM
_LEGACY_LOSS_KEYS = {f"w_{k}": k for k in ("focal", "sem_scal", "geo_scal", "dice", "lovasz", "depth", "bev")}


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (docs/design.md#losses): the `[loss]` TOML table (flat `w_focal = ...` keys are
    read too)."""

    focal: float = 1.0
    sem_scal: float = 1.0
    geo_scal: float = 1.0
    dice: float = 1.0
    lovasz: float = 1.0
    depth: float = 1.0
    bev: float = 1.0

    def __post_init__(self) -> None:
        bad = [f"loss.{f.name} = {getattr(self, f.name)}" for f in dataclasses.fields(self)
               if not (math.isfinite(getattr(self, f.name)) and getattr(self, f.name) >= 0)]
        if bad:
            raise ConfigError("bad training config: " + "; ".join(bad) + " (loss weights must be finite and >= 0)")


@dataclass(frozen=True)
class TrainConfig:
    """A training run. Defaults follow the paper's recipe (docs/design.md#training-recipe); see docs/training.md.

    Batch and schedule: `batch_size` is the GLOBAL batch (all ranks, all accumulation micro-steps);
    each optimizer step consumes exactly `batch_size` samples whatever the number of processes, and
    the schedule (warm-up, cosine) is a function of samples seen, so changing GPU count or batch size
    does not change how many samples are seen. The learning rate actually used is
    `lr * scale(batch_size / lr_base_batch)` with scale = identity ("linear"), sqrt ("sqrt") or 1 ("none").
    """

    # data
    store: str = "data.zarr"
    train_split: str = "train"
    val_split: str | None = None  # None: "val" when the store has it, else the store's only split
    workers: int = 2
    limit_train_samples: int = 0  # > 0: only the first N training samples (smoke runs, tests)
    augment: bool = True  # image (resize/crop/flip/rotate) + BEV (flip) augmentation
    noise_images: bool = False  # ablation: replace every camera image by Gaussian noise (train and val)
    # model
    preset: str = "nano"
    head: str = "fastocc"
    view_transform: str = "lss"  # lss | attention (spatial cross-attention, the SurroundOcc* row)
    input_hw: tuple[int, int] | None = None  # None = the preset's input size
    num_history: int | None = None  # None = the preset's (temporal models train scene-sequentially)
    interp_features: bool = True  # ablation: False = FastOcc head without interpolated image features
    bev_height: str = "repeat"  # with interp_features off: repeat (constant along z) | unfold (channel-to-height)
    # concat | cached (each frame reduced once to temporal_channels, when current) | recurrent (one state)
    temporal_fusion: str = "concat"
    temporal_channels: int | None = None  # C_r / C_s; None = the fusion's measured width (TEMPORAL_CHANNELS)
    temporal_unroll: int = 4  # recurrent only: frames unrolled with gradient in training (truncated BPTT)
    temporal_grad_history: bool = False  # cached only: train the reduction through the queued frames too
    zero_history_fusion: bool = False  # ablation: the temporal fusion layer without history (num_history 0)
    scene_sequential: bool = False  # walk scenes in order also for single-frame models (history ablation)
    pretrained: str | None = None  # backbone weights: torchvision state dict or mmdet/mmdet3d checkpoint
    checkpoint_backbone: bool = False  # activation checkpointing of the image backbone (saves memory)
    # optimisation
    epochs: int = 24
    batch_size: int = 1
    micro_batch: int = 0  # per-process samples per forward pass; 0 = batch_size / world size
    lr: float = 2e-4
    lr_base_batch: int = 16
    lr_scaling: str = "linear"  # linear | sqrt | none
    weight_decay: float = 1e-2
    warmup_epochs: float = 0.2
    min_lr_ratio: float = 1e-3  # cosine floor as a fraction of the peak learning rate
    grad_clip: float = 5.0  # max global grad norm; 0 = off
    ema: bool = True
    ema_decay: float = 0.999  # ramps as min(decay, (1 + n) / (10 + n)) over optimizer steps n
    # losses (docs/design.md#losses)
    camera_mask: bool = True  # voxel losses on mask_camera = 1 only (matches Occ3D mIoU; see docs)
    class_weights: bool = True  # focal weights 1 / ln(f_c + 0.001) from the training split's counts
    loss: LossWeights = dataclasses.field(default_factory=LossWeights)
    # run
    out: str = "runs/fastocc"
    device: str = "auto"  # auto | cpu | cuda
    amp: bool = True  # bf16 autocast on CUDA (ignored on CPU)
    seed: int = 0
    deterministic: bool = False  # torch.use_deterministic_algorithms (exact resume on GPU)
    threads: int = 0  # torch CPU threads per process; 0 = torch's default
    val_every: int = 1  # epochs; 0 = never
    val_rayiou: bool = True
    keep_epochs: int = 3  # epoch checkpoints kept besides last/best
    save_every_steps: int = 0  # also write `last` every N optimizer steps (0 = at epoch ends only)
    max_nonfinite: int = 5  # stop after this many non-finite losses in a row
    log_every: int = 10  # optimizer steps between metrics.jsonl records
    init_from: str | None = None  # start a new run from this checkpoint's weights (model, and EMA if kept)
    warn_signal: str = "USR1"  # besides SIGTERM, this signal stops at the next step boundary, saving last.pt
    dist_timeout: int = 1800  # seconds a collective may wait for the other processes before failing

    def __post_init__(self) -> None:
        bad = []
        if self.preset not in PRESETS:
            bad.append(f"preset {self.preset!r} (choose from {sorted(PRESETS)})")
        if self.head not in {h.value for h in HeadKind}:
            bad.append(f"head {self.head!r} (choose from {[h.value for h in HeadKind]})")
        if self.lr_scaling not in ("linear", "sqrt", "none"):
            bad.append(f"lr_scaling {self.lr_scaling!r} (linear, sqrt or none)")
        if self.device not in ("auto", "cpu", "cuda"):
            bad.append(f"device {self.device!r} (auto, cpu or cuda)")
        for name in ("epochs", "batch_size", "lr_base_batch"):
            if getattr(self, name) < 1:
                bad.append(f"{name} = {getattr(self, name)} (must be >= 1)")
        for name in ("workers", "micro_batch", "limit_train_samples", "val_every", "keep_epochs",
                     "save_every_steps", "threads"):
            if getattr(self, name) < 0:
                bad.append(f"{name} = {getattr(self, name)} (must be >= 0)")
        if self.warn_signal not in WARN_SIGNALS:
            bad.append(f"warn_signal {self.warn_signal!r} (choose from {list(WARN_SIGNALS)})")
        if self.dist_timeout < 1:
            bad.append(f"dist_timeout = {self.dist_timeout} (must be >= 1 second)")
        if self.max_nonfinite < 1:
            bad.append(f"max_nonfinite = {self.max_nonfinite} (must be >= 1)")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            bad.append(f"lr = {self.lr} (must be > 0)")
        if not 0.0 <= self.ema_decay < 1.0:
            bad.append(f"ema_decay = {self.ema_decay} (must be in [0, 1))")
        if self.warmup_epochs < 0 or self.warmup_epochs > self.epochs:
            bad.append(f"warmup_epochs = {self.warmup_epochs} (must be in [0, epochs])")
        if not self.interp_features and self.head != HeadKind.FASTOCC.value:
            bad.append(f"interp_features = false with head {self.head!r} (only the fastocc head has them)")
        if self.bev_height not in {b.value for b in BevHeight}:
            bad.append(f"bev_height {self.bev_height!r} (choose from {[b.value for b in BevHeight]})")
        elif self.bev_height != BevHeight.REPEAT.value and (self.interp_features or self.head != HeadKind.FASTOCC):
            bad.append(f"bev_height = {self.bev_height!r} needs head fastocc and interp_features = false")
        if self.temporal_fusion not in {k.value for k in TemporalFusionKind}:
            kinds = [k.value for k in TemporalFusionKind]
            bad.append(f"temporal_fusion {self.temporal_fusion!r} (choose from {kinds})")
        if self.temporal_channels is not None and self.temporal_channels < 1:
            bad.append(f"temporal_channels = {self.temporal_channels} (must be >= 1)")
        if self.temporal_grad_history and self.temporal_fusion != TemporalFusionKind.CACHED.value:
            bad.append("temporal_grad_history needs temporal_fusion 'cached'")
        if self.temporal_unroll < 1:
            bad.append(f"temporal_unroll = {self.temporal_unroll} (must be >= 1)")
        if self.view_transform not in {k.value for k in ViewTransformKind}:
            bad.append(f"view_transform {self.view_transform!r} (choose from {[k.value for k in ViewTransformKind]})")
        if self.input_hw is not None and any(v <= 0 or v % 16 for v in self.input_hw):
            bad.append(f"input_hw = {self.input_hw} (positive multiples of 16)")
        if bad:
            raise ConfigError("bad training config: " + "; ".join(bad))

    # -- derived -------------------------------------------------------------------------------
    def model_config(self) -> ModelConfig:
        changes: dict[str, Any] = {"head": HeadKind(self.head), "interp_features": self.interp_features,
                                   "bev_height": BevHeight(self.bev_height),
                                   "temporal_fusion": TemporalFusionKind(self.temporal_fusion),
                                   "temporal_channels": self.temporal_channels,
                                   "temporal_grad_history": self.temporal_grad_history,
                                   "temporal_unroll": self.temporal_unroll,
                                   "zero_history_fusion": self.zero_history_fusion,
                                   "view_transform": ViewTransformKind(self.view_transform)}
        if self.input_hw is not None:
            changes["input_hw"] = tuple(self.input_hw)
        if self.num_history is not None:
            changes["num_history"] = self.num_history
        return preset(self.preset, **changes)

    def lr_factor(self) -> float:
        """The scaling applied to `lr` for the global batch size (printed at start)."""
        r = self.batch_size / self.lr_base_batch
        return {"linear": r, "sqrt": math.sqrt(r), "none": 1.0}[self.lr_scaling]

    def peak_lr(self) -> float:
        return self.lr * self.lr_factor()

    def lr_at(self, samples_seen: int, samples_per_epoch: int) -> float:
        """Linear warm-up to the peak over `warmup_epochs`, then cosine to `min_lr_ratio * peak` at the end."""
        peak = self.peak_lr()
        total = max(1, self.epochs * samples_per_epoch)
        warm = self.warmup_epochs * samples_per_epoch
        if warm > 0 and samples_seen < warm:
            return peak * (samples_seen + 1) / (warm + 1)  # never exactly 0 at the first step
        t = min(1.0, (samples_seen - warm) / max(1.0, total - warm))
        return peak * (self.min_lr_ratio + (1 - self.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(dataclasses.asdict(self)))


# Fields that may differ between a run and its --resume (they change neither the model nor the
# sample stream nor the optimisation): where things run and how often things are logged/saved.
# `epochs` may grow (the cosine is stretched to the new end, see `lr_at`); `init_from` only acts on a new run.
RESUME_MAY_CHANGE = frozenset({"store", "workers", "device", "out", "threads", "val_every", "val_rayiou",
                               "keep_epochs", "save_every_steps", "max_nonfinite", "log_every", "pretrained",
                               "init_from", "warn_signal", "dist_timeout", "epochs", "val_split"})


def _coerce(field: dataclasses.Field, value: Any) -> Any:
    """TOML value -> the field's type, with a clear error naming the key."""
    name, default = field.name, field.default
    if field.name == "input_hw":
        if value is None:
            return None
        if not (isinstance(value, list | tuple) and len(value) == 2 and all(isinstance(v, int) for v in value)):
            raise ConfigError(f"config key {name!r}: expected [height, width] integers, got {value!r}")
        return (int(value[0]), int(value[1]))
    if name == "loss":
        if isinstance(value, LossWeights):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"config key 'loss': expected a table of loss weights, got {value!r}")
        known = {f.name: f for f in dataclasses.fields(LossWeights)}
        unknown = sorted(set(value) - set(known))
        if unknown:
            raise ConfigError(f"unknown [loss] key(s) {unknown}; known: {', '.join(known)}")
        return dataclasses.replace(LossWeights(), **{k: _coerce(known[k], v) for k, v in value.items()})
    if name in ("num_history", "temporal_channels", "pretrained", "init_from"):
        ok = value is None or isinstance(value, str if name in ("pretrained", "init_from") else int)
        if not ok or isinstance(value, bool):
            raise ConfigError(f"config key {name!r}: bad value {value!r}")
        return value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"config key {name!r}: expected true/false, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key {name!r}: expected an integer, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"config key {name!r}: expected a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"config key {name!r}: expected a string, got {value!r}")
        return value
    return value


def _lift_legacy_loss_keys(d: dict[str, Any]) -> dict[str, Any]:
    """Flat `w_focal = ...` keys (configs before the `[loss]` table) -> `loss = {focal = ...}`."""
    flat = {k: v for k, v in d.items() if k in _LEGACY_LOSS_KEYS}
    if not flat:
        return d
    out = {k: v for k, v in d.items() if k not in _LEGACY_LOSS_KEYS}
    table = out.get("loss")
    table = dict(table) if isinstance(table, dict) else ({} if table is None else table)
    if isinstance(table, dict):
        for k, v in flat.items():
            if _LEGACY_LOSS_KEYS[k] in table:
                raise ConfigError(f"loss weight {_LEGACY_LOSS_KEYS[k]!r} given twice ({k} and [loss])")
            table[_LEGACY_LOSS_KEYS[k]] = v
    out["loss"] = table
    return out


def config_from_dict(d: dict[str, Any], base: TrainConfig | None = None) -> TrainConfig:
    """Apply `d` on top of `base` (default TrainConfig()); an unknown key is an error naming it.
    `loss` may be a partial table; it updates the base's weights."""
    d = _lift_legacy_loss_keys(d)
    if isinstance(d.get("loss"), dict) and base is not None:
        d = {**d, "loss": {**dataclasses.asdict(base.loss), **d["loss"]}}
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ConfigError(f"unknown config key(s) {unknown}; known keys: {', '.join(sorted(fields))}")
    changes = {k: _coerce(fields[k], v) for k, v in d.items()}
    return dataclasses.replace(base or TrainConfig(), **changes)


def load_config(path: str | Path | None, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Defaults < TOML file < overrides (None values in overrides mean "not given")."""
    cfg = TrainConfig()
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: no such config file")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        if set(data) == {"train"} and isinstance(data["train"], dict):
            data = data["train"]
        try:
            cfg = config_from_dict(data, cfg)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    return config_from_dict(given, cfg) if given else cfg


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(v)


def config_to_toml(cfg: TrainConfig) -> str:
    """The resolved config as a `[train]` TOML table with a `[train.loss]` sub-table (None fields are left
    out = "the preset's")."""
    d = cfg.to_dict()
    loss = d.pop("loss")
    lines = ["# resolved by fastocc train; reuse with --config", "[train]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in d.items() if v is not None]
    lines += ["", "[train.loss]"] + [f"{k} = {_toml_value(v)}" for k, v in loss.items()]
    return "\n".join(lines) + "\n"


def flat_config(d: dict[str, Any]) -> dict[str, Any]:
    """A config dict (as saved, old flat loss keys allowed) with the loss table as `loss.<term>` keys."""
    d = _lift_legacy_loss_keys(dict(d))
    loss = d.pop("loss", None) or {}
    return {**d, **{f"loss.{k}": v for k, v in loss.items()}}


def incompatible_fields(saved: dict[str, Any], cfg: TrainConfig) -> list[str]:
    """Fields (`loss.<term>` for weights) whose values differ between a saved config dict and `cfg`, other
    than RESUME_MAY_CHANGE; `epochs` counts only when it shrinks."""
    was, now = _built_width(flat_config(saved)), _built_width(flat_config(cfg.to_dict()))
    bad = sorted(k for k in set(was) | set(now)
                 if k not in RESUME_MAY_CHANGE and was.get(k, _DEFAULTS.get(k)) != now.get(k))
    if int(was.get("epochs", 0)) > cfg.epochs:
        bad = sorted([*bad, "epochs"])
    return bad


def _built_width(d: dict[str, Any]) -> dict[str, Any]:
    """`temporal_channels` as the width the network gets, so that None and the number it stands for compare
    equal (runs saved before None meant "the fusion's default")."""
    m = ModelConfig(temporal_fusion=d.get("temporal_fusion", "concat"), temporal_channels=d.get("temporal_channels"))
    return {**d, "temporal_channels": m.temporal_width}


_DEFAULTS = flat_config(TrainConfig().to_dict())  # fields added after a checkpoint was written compare as defaults
