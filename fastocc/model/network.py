"""The FastOcc network: stages composed, each a separate module (docs/design.md#the-network)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from .attention import SpatialCrossAttention
from .config import HeadKind, ModelConfig, TemporalFusionKind, ViewTransformKind
from .heads import BEVMultiHotHead, build_head
from .inputs import ModelOutputs, SceneInputs
from .neck import FPNNeck
from .pretrained import load_backbone
from .recurrent import RecurrentFusion
from .resnet import resnet
from .temporal import TemporalFusion
from .view_transform import DepthNet, LSSPooling

__all__ = ["FastOcc", "collapse_z"]


def collapse_z(volume: Tensor) -> Tensor:
    """`(B, C, X, Y, Z)` -> `(B, C*Z, X, Y)` with channel index c Z + k."""
    B, C, X, Y, Z = volume.shape
    return volume.permute(0, 1, 4, 2, 3).reshape(B, C * Z, X, Y)


def _temporal(cfg: ModelConfig, channels: int) -> TemporalFusion | RecurrentFusion | None:
    """The temporal fusion layer of `cfg` on BEV maps of `channels` (None: a single-frame model)."""
    if not cfg.has_temporal:
        return None
    if cfg.temporal_fusion is TemporalFusionKind.RECURRENT:
        return RecurrentFusion(channels, cfg.coarse_grid, cfg.temporal_width, cfg.temporal_unroll)
    return TemporalFusion(channels, cfg.num_history, cfg.coarse_grid, cfg.temporal_fusion, cfg.temporal_width,
                          cfg.temporal_grad_history)


class FastOcc(nn.Module):
    """Image stage (ResNet + FPN) -> view stage (depth net and LSS pooling, or spatial cross-attention; optional
    temporal fusion) ->
    head stage (FastOcc head or a baseline, plus the BEV multi-hot head in training)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        z = cfg.coarse_grid.shape[2]
        # channels-last: oneDNN's convolutions run a ResNet-50 forward+backward ~1.3x faster on CPU
        self.backbone = resnet(cfg.backbone.depth, cfg.backbone.base_width).to(memory_format=torch.channels_last)
        self.neck = FPNNeck(self.backbone.out_channels, cfg.neck_channels)
        self.depth_net: DepthNet | None = None
        self.pooling: LSSPooling | None = None
        self.attention: SpatialCrossAttention | None = None
        if cfg.view_transform == ViewTransformKind.ATTENTION:
            self.attention = SpatialCrossAttention(cfg)
        else:
            self.depth_net = DepthNet(cfg.neck_channels, cfg.context_channels, cfg.depth_bins.count)
            self.pooling = LSSPooling(cfg.coarse_grid, cfg.depth_bins.centres(), cfg.input_hw, cfg.stride)
        self.temporal = _temporal(cfg, cfg.context_channels * z)
        self.head = build_head(cfg)
        use_bev_head = cfg.bev_head and cfg.head is HeadKind.FASTOCC
        self.bev_head = (
            BEVMultiHotHead(cfg.bev_channels, cfg.num_classes, cfg.fine_grid.shape[:2]) if use_bev_head else None
        )

    def load_pretrained_backbone(self, path: str | Path) -> str:
        """Load a torchvision ResNet state dict or an mmdet/mmdet3d checkpoint's ResNet into the backbone;
        returns one line saying what was loaded (`pretrained.load_backbone`)."""
        return load_backbone(self.backbone, path)

    def clear_caches(self) -> None:
        """Forget cached geometry (LSS indices, sampling weights) and the temporal queue."""
        for vt in (self.pooling, self.attention):
            if vt is not None:
                vt.clear_cache()
        sampler = getattr(self.head, "sampler", None)
        if sampler is not None:
            sampler.clear_cache()
        if self.temporal is not None:
            self.temporal.reset()

    def image_stage(self, images: Tensor) -> Tensor:
        """`(B, N, 3, H, W)` -> F `(B*N, C1, H/16, W/16)` (contiguous)."""
        x = images.flatten(0, 1).contiguous(memory_format=torch.channels_last)
        return self.neck(self.backbone(x)).contiguous()

    def view_stage(self, feat: Tensor, inputs: SceneInputs) -> tuple[Tensor | None, Tensor]:
        """F -> depth `(B*N, 88, h, w)` (None for the attention view transform, which has no depth net) and
        V_B with z collapsed `(B, C2*8, 100, 100)` (temporally fused)."""
        if self.attention is not None:
            depth, bev = None, collapse_z(self.attention(feat, inputs))
        else:
            depth, context = self.depth_net(feat)
            bev = collapse_z(self.pooling(depth, context, inputs))
        if self.temporal is not None:
            bev = self.temporal(bev, inputs)
        return depth, bev

    def head_stage(self, feat: Tensor, bev: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor | None]:
        """-> voxel logits `(B, 18, 200, 200, 16)` and BEV logits `(B, 18, 200, 200)` (training only)."""
        logits, bev_map = self.head(feat, bev, inputs)
        bev_logits = self.bev_head(bev_map) if self.bev_head is not None and self.training else None
        return logits, bev_logits

    def forward(self, inputs: SceneInputs) -> ModelOutputs:
        feat = self.image_stage(inputs.images)
        depth, bev = self.view_stage(feat, inputs)
        logits, bev_logits = self.head_stage(feat, bev, inputs)
        return ModelOutputs(voxel_logits=logits, depth_probs=depth, bev_logits=bev_logits)
