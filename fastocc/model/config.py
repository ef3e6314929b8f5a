"""Frozen network configs and the four presets (docs/design.md#the-network)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Literal

from occdata.constants import GRID, NUM_CLASSES, OccGrid

__all__ = [
    "COARSE_GRID",
    "DEPTH_BINS",
    "BackboneConfig",
    "BevHeight",
    "HeadKind",
    "ModelConfig",
    "PRESETS",
    "TEMPORAL_CHANNELS",
    "TemporalFusionKind",
    "ViewTransformKind",
    "preset",
]

COARSE_GRID = OccGrid(voxel_size=0.8)  # 100 x 100 x 8, the LSS target grid V_B


@dataclass(frozen=True)
class DepthBins:
    """Depth bins [lower, upper) with `step` metres: bin k covers [lower + k step, lower + (k+1) step)."""

    lower: float = 1.0
    upper: float = 45.0
    step: float = 0.5

    @property
    def count(self) -> int:
        return round((self.upper - self.lower) / self.step)

    def centres(self) -> list[float]:
        """Bin centres in metres; frustum points are lifted at the centre (not the lower edge) of a bin."""
        return [self.lower + self.step * (k + 0.5) for k in range(self.count)]


DEPTH_BINS = DepthBins()  # 88 bins


class HeadKind(StrEnum):
    """Which 3D-side head decodes V_B (the paper's ablation): a plain field, not a registry."""

    FASTOCC = "fastocc"  # 2D BEV FCN + interpolated image features (FastOcc)
    FCN3D = "3dfcn"  # 3D FCN on V_B ("Baseline+")
    DECONV = "deconv"  # 3D deconvolution on V_B ("Baseline")


class TemporalFusionKind(StrEnum):
    """How the temporal queue is fused (docs/model.md, "Temporal fusion")."""

    CONCAT = "concat"  # queue of full V_B maps (C2*8 channels); 1x1 conv over all T + 1 of them
    CACHED = "cached"  # each frame reduced once to C_r channels when current; warp + small fusion per frame
    RECURRENT = "recurrent"  # one state of C_s channels carried forward: warp + a gated (ConvGRU) update per frame


# The width each fusion was measured at (docs/ablations.md: `hist16cached` C_r = 16, `hist16rec` C_s = 32):
# its default when `temporal_channels` is not given. "concat" queues full maps and has no such width.
TEMPORAL_CHANNELS: dict[TemporalFusionKind, int] = {TemporalFusionKind.CACHED: 16, TemporalFusionKind.RECURRENT: 32}


class ViewTransformKind(StrEnum):
    """How image features become the coarse voxel volume V_B (paper Table II)."""

    LSS = "lss"  # depth distribution x context, voxel pooling (BEVDepth; FastOcc and the baselines)
    ATTENTION = "attention"  # spatial cross-attention from voxel queries, deformable sampling (SurroundOcc*)


class BevHeight(StrEnum):
    """How the FastOcc head gives height to its BEV part when `interp_features` is off (paper Table IV)."""

    REPEAT = "repeat"  # the BEV feature repeated along z: constant over the 16 heights
    UNFOLD = "unfold"  # channel-to-height: W_B outputs C_f x 16 channels, unfolded into the 16 height bins


@dataclass(frozen=True)
class BackboneConfig:
    """torchvision-layout ResNet; `base_width` 64 is torchvision's, smaller values give narrow nets."""

    depth: Literal[18, 34, 50, 101] = 50
    base_width: int = 64


@dataclass(frozen=True)
class ModelConfig:
    """Everything that sizes the network. Channel names follow docs/design.md#the-network (C1, C2, C3)."""

    name: str = "tiny"
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    input_hw: tuple[int, int] = (320, 800)
    num_cams: int = 6  # the rig's cameras: `fastocc train` sets the store's count (the weights do not depend on it)
    neck_channels: int = 256  # C1: image feature map F at stride 16
    context_channels: int = 64  # C2: LSS context per voxel of V_B; also C of the BEV encoder (2C/4C/8C)
    bev_channels: int = 128  # C3: decoded BEV map B at 100 x 100
    fuse_channels: int = 64  # C_f: fused voxel feature V at 200 x 200 x 16
    head: HeadKind = HeadKind.FASTOCC
    view_transform: ViewTransformKind = ViewTransformKind.LSS
    attention_heads: int = 4  # spatial cross-attention (view_transform "attention"): heads, C2 divisible by it
    attention_points: int = 4  # deformable samples per head and camera
    num_history: int = 0  # previous frames in the temporal queue (0 = single frame; paper's base: 16)
    bev_head: bool = True  # auxiliary multi-hot BEV head (training only; FastOcc head only)
    # Ablation (paper Table IV): False drops the interpolated image features P from the FastOcc head, so the
    # fused voxel feature is the upsampled, z-repeated BEV map alone (constant along z). FastOcc head only.
    interp_features: bool = True
    # With interp_features off: REPEAT (constant along z) or UNFOLD (channels unfolded into the height bins).
    bev_height: BevHeight = BevHeight.REPEAT
    temporal_fusion: TemporalFusionKind = TemporalFusionKind.CONCAT
    # C_r of a frame in the "cached" queue / C_s of the "recurrent" state; None: the fusion's TEMPORAL_CHANNELS
    temporal_channels: int | None = None
    # "recurrent" only: frames the recurrence is unrolled over with gradient in training (truncated BPTT)
    temporal_unroll: int = 4
    # "cached" only, a training control: the training queue keeps each frame's full map (detached) and
    # the reduction runs on the queued maps with gradient, so it learns from the history too; the
    # forward values equal the cached queue's (reduce, then warp), and inference keeps the cache.
    temporal_grad_history: bool = False
    # Fusion-layer control of the history ablation: build the temporal fusion layer also when num_history
    # is 0 (the current frame alone through it), so a 0-frame row differs from a history row only by history.
    zero_history_fusion: bool = False
    num_classes: int = NUM_CLASSES
    stride: int = 16
    fine_grid: OccGrid = GRID
    coarse_grid: OccGrid = COARSE_GRID
    depth_bins: DepthBins = DEPTH_BINS

    def __post_init__(self) -> None:
        bad = []
        kinds = (("head", HeadKind), ("bev_height", BevHeight), ("temporal_fusion", TemporalFusionKind),
                 ("view_transform", ViewTransformKind))
        for name, kind in kinds:
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))  # plain strings -> the enum
            except ValueError:
                bad.append(f"{name} = {getattr(self, name)!r} (choose from {[k.value for k in kind]})")
        if self.num_history < 0:
            bad.append(f"num_history = {self.num_history} (must be >= 0)")
        if self.temporal_channels is not None and self.temporal_channels < 1:
            bad.append(f"temporal_channels = {self.temporal_channels} (must be >= 1)")
        if self.temporal_grad_history and self.temporal_fusion != TemporalFusionKind.CACHED:
            bad.append("temporal_grad_history needs temporal_fusion = 'cached'")
        if self.temporal_unroll < 1:
            bad.append(f"temporal_unroll = {self.temporal_unroll} (must be >= 1)")
        if self.temporal_fusion == TemporalFusionKind.RECURRENT and self.zero_history_fusion:
            bad.append("zero_history_fusion is a control of the queue fusions, not of 'recurrent'")
        if self.bev_height == BevHeight.UNFOLD and (self.interp_features or self.head != HeadKind.FASTOCC):
            bad.append(f"bev_height = {self.bev_height!s} needs the fastocc head with interp_features off")
        if self.attention_heads < 1 or self.attention_points < 1 or self.context_channels % self.attention_heads:
            bad.append(f"attention_heads = {self.attention_heads}, attention_points = {self.attention_points} (>= 1; "
                       f"context_channels {self.context_channels} divisible by the heads)")
        if bad:
            raise ValueError("bad model config: " + "; ".join(bad))

    @property
    def has_temporal(self) -> bool:
        """Whether the network builds a temporal fusion layer (history, or the zero-history control)."""
        return self.num_history > 0 or self.zero_history_fusion

    @property
    def temporal_width(self) -> int:
        """C_r / C_s: `temporal_channels`, else the fusion's measured width ("concat" does not use it)."""
        if self.temporal_channels is not None:
            return self.temporal_channels
        return TEMPORAL_CHANNELS.get(self.temporal_fusion, TEMPORAL_CHANNELS[TemporalFusionKind.CACHED])

    @property
    def feat_hw(self) -> tuple[int, int]:
        """Image feature map size (h, w) = input / 16 (inputs must be multiples of 16)."""
        return self.input_hw[0] // self.stride, self.input_hw[1] // self.stride

    def replace(self, **changes: Any) -> ModelConfig:
        return dataclasses.replace(self, **changes)


PRESETS: dict[str, ModelConfig] = {
    "nano": ModelConfig(
        name="nano",
        backbone=BackboneConfig(depth=18, base_width=16),
        input_hw=(128, 352),
        neck_channels=32,
        context_channels=16,
        bev_channels=32,
        fuse_channels=16,
    ),
    "tiny": ModelConfig(name="tiny", backbone=BackboneConfig(depth=50), input_hw=(320, 800)),
    "small": ModelConfig(name="small", backbone=BackboneConfig(depth=101), input_hw=(320, 800)),
    "base": ModelConfig(name="base", backbone=BackboneConfig(depth=101), input_hw=(640, 1600), num_history=16),
}


def preset(name: str, **overrides: Any) -> ModelConfig:
    """A preset by name with optional field overrides, e.g. `preset("tiny", head=HeadKind.FCN3D)`."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **overrides)
