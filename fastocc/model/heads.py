"""3D-side heads on the pooled volume V_B: FastOcc's (2D BEV FCN + interpolation + fusion) and the paper's
two baselines (3D FCN "Baseline+", 3D deconvolution "Baseline"); plus the training-only BEV head."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .bev_decoder import BEVDecoder
from .config import BevHeight, HeadKind, ModelConfig
from .inputs import SceneInputs
from .interp import InterpolationSampler

__all__ = ["BEVMultiHotHead", "DeconvHead", "FCN3DHead", "FastOccHead", "build_head", "uncollapse_z"]


def uncollapse_z(bev: Tensor, z: int) -> Tensor:
    """`(B, C*Z, X, Y)` (z collapsed, channel = c Z + k) -> `(B, C, X, Y, Z)`."""
    B, CZ, X, Y = bev.shape
    return bev.view(B, CZ // z, z, X, Y).permute(0, 1, 3, 4, 2)


class FastOccHead(nn.Module):
    """BEV decoder -> B; interpolation sampling -> P; fusion of z-repeated B with P; voxel classifier.

    The fusion layer is one 1x1x1 conv on concat(B_z, P): W [B_z; P] + b = W_B B_z + W_P P + b. Both parts
    are applied where they are cheapest, which is exact because upsampling, z-repetition and sampling are
    linear with weights summing to 1: W_B at 100 x 100 before upsampling, W_P on the image map before
    sampling. Nothing of width C3 + C1 is ever materialised at 200 x 200 x 16.

    With `cfg.interp_features` False (the components ablation) the head has no W_P and no sampler, and the
    fused feature is the BEV part alone. `cfg.bev_height` says how it varies with height: "repeat" gives
    relu(W_B B_z + b), constant along z, so the classifier runs once per BEV cell and its logits are
    repeated over the Z levels (exact: the classifier is per voxel); "unfold" (channel-to-height) has W_B
    output C_f x Z channels, channel k C_f + c being feature c at height bin k, so the BEV map alone gives
    every one of the Z heights its own feature.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        z = cfg.coarse_grid.shape[2]
        c2, c3, cf = cfg.context_channels, cfg.bev_channels, cfg.fuse_channels
        self.fine_shape = cfg.fine_grid.shape
        self.decoder = BEVDecoder(2, c2 * z, c2, c3)
        self.height_bins = cfg.fine_grid.shape[2] if cfg.bev_height == BevHeight.UNFOLD else 1
        self.fuse_bev = nn.Conv2d(c3, cf * self.height_bins, 1)  # W_B and the fusion bias
        self.fuse_img: nn.Conv2d | None = None  # W_P
        self.sampler: InterpolationSampler | None = None
        if cfg.interp_features:
            self.fuse_img = nn.Conv2d(cfg.neck_channels, cf, 1, bias=False)
            self.sampler = InterpolationSampler(cfg.fine_grid, cfg.input_hw, cfg.stride)
        self.classifier = nn.Linear(cf, cfg.num_classes)

    def forward(self, feat: Tensor, bev: Tensor, inputs: SceneInputs) -> tuple[Tensor, Tensor]:
        """feat `(B*N, C1, h, w)`, bev `(B, C2*8, 100, 100)` ->
        logits `(B, 18, 200, 200, 16)`, B `(B, C3, 100, 100)`."""
        bev_map = self.decoder(bev)
        bev_z = self.bev_part(bev_map)  # (B, X, Y, 1 or Z, Cf)
        if self.sampler is None or self.fuse_img is None:  # ablation: no interpolated image features
            logits = self.classifier(F.relu(bev_z)).expand(-1, -1, -1, self.fine_shape[2], -1)
            return logits.permute(0, 4, 1, 2, 3).contiguous(), bev_map
        img_part = self.sampler(self.fuse_img(feat), inputs)  # (B, X, Y, Z, Cf)
        logits = self.classifier(F.relu(img_part + bev_z))  # (B, X, Y, Z, 18)
        return logits.permute(0, 4, 1, 2, 3), bev_map


    def bev_part(self, bev_map: Tensor) -> Tensor:
        """W_B B + b upsampled to the fine grid: `(B, C3, 100, 100)` -> `(B, X, Y, Zb, Cf)`, Zb = 1 (repeated
        along z by broadcasting) or Z ("unfold": channel k C_f + c is feature c of height bin k)."""
        X, Y, _ = self.fine_shape
        x = F.interpolate(self.fuse_bev(bev_map), size=(X, Y), mode="bilinear", align_corners=False)
        B, Cf = x.shape[0], x.shape[1] // self.height_bins
        return x.view(B, self.height_bins, Cf, X, Y).permute(0, 3, 4, 1, 2)


class FCN3DHead(nn.Module):
    """Baseline+: the same encoder/FPN design in 3D on V_B (C2, 100, 100, 8), then x2 trilinear upsampling
    to the fine grid and a per-voxel classifier."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c2, c3, cf = cfg.context_channels, cfg.bev_channels, cfg.fuse_channels
        self.z = cfg.coarse_grid.shape[2]
        self.fine_shape = cfg.fine_grid.shape
        self.decoder = BEVDecoder(3, c2, c2, c3)
        self.proj = nn.Conv3d(c3, cf, 1)  # before upsampling: same commutation as FastOccHead's fusion
        self.classifier = nn.Conv3d(cf, cfg.num_classes, 1)

    def forward(self, feat: Tensor, bev: Tensor, inputs: SceneInputs) -> tuple[Tensor, None]:
        x = self.proj(self.decoder(uncollapse_z(bev, self.z)))
        x = F.relu(F.interpolate(x, size=self.fine_shape, mode="trilinear", align_corners=False))
        return self.classifier(x), None


class DeconvHead(nn.Module):
    """Baseline: one 3x3x3 conv on V_B, a stride-2 3D transposed conv to the fine grid, a classifier."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c2, c3, cf = cfg.context_channels, cfg.bev_channels, cfg.fuse_channels
        self.z = cfg.coarse_grid.shape[2]
        self.body = nn.Sequential(
            nn.Conv3d(c2, c3, 3, padding=1, bias=False),
            nn.BatchNorm3d(c3),
            nn.ReLU(inplace=True),
            nn.ConvTranspose3d(c3, cf, 2, stride=2, bias=False),
            nn.BatchNorm3d(cf),
            nn.ReLU(inplace=True),
        )
        self.classifier = nn.Conv3d(cf, cfg.num_classes, 1)

    def forward(self, feat: Tensor, bev: Tensor, inputs: SceneInputs) -> tuple[Tensor, None]:
        return self.classifier(self.body(uncollapse_z(bev, self.z))), None


class BEVMultiHotHead(nn.Module):
    """UNet-like 2D head: B `(B, C3, 100, 100)` -> multi-hot logits `(B, M, 200, 200)` (M = 18, free kept).

    One down/up level with a skip at 100 x 100; the logits are upsampled bilinearly to 200 x 200 (convs at
    200 x 200 would cost as much as the rest of the head on CPU).
    """

    def __init__(self, c3: int, num_classes: int, out_hw: tuple[int, int]) -> None:
        super().__init__()
        self.out_hw = out_hw

        def block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
            return nn.Sequential(
                nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)
            )

        self.enc1 = block(c3, c3)
        self.enc2 = block(c3, 2 * c3, 2)
        self.dec1 = block(3 * c3, c3)
        self.out = nn.Conv2d(c3, num_classes, 1)

    def forward(self, bev_map: Tensor) -> Tensor:
        e1 = self.enc1(bev_map)
        e2 = self.enc2(e1)
        d1 = self.dec1(torch.cat([e1, F.interpolate(e2, size=e1.shape[2:], mode="bilinear", align_corners=False)], 1))
        return F.interpolate(self.out(d1), size=self.out_hw, mode="bilinear", align_corners=False)


def build_head(cfg: ModelConfig) -> nn.Module:
    """The head selected by `cfg.head`."""
    if cfg.head is HeadKind.FASTOCC:
        return FastOccHead(cfg)
    if cfg.head is HeadKind.FCN3D:
        return FCN3DHead(cfg)
    if cfg.head is HeadKind.DECONV:
        return DeconvHead(cfg)
    raise ValueError(f"unknown head {cfg.head!r}")
