"""ResNet-18-style encoder + FPN decoder, in 2D (FastOcc's BEV decoder) or 3D (the 3D FCN baseline)."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["BEVDecoder", "FPNDecoder", "ResidualBlock", "ResidualEncoder"]


def conv(dims: int, c_in: int, c_out: int, k: int, stride: int = 1, bias: bool = False) -> nn.Module:
    cls = nn.Conv2d if dims == 2 else nn.Conv3d
    return cls(c_in, c_out, k, stride=stride, padding=k // 2, bias=bias)


def norm(dims: int, c: int) -> nn.Module:
    return nn.BatchNorm2d(c) if dims == 2 else nn.BatchNorm3d(c)


class ResidualBlock(nn.Module):
    """BasicBlock (two 3x3 / 3x3x3 convs) in `dims` dimensions, with a 1x1 projection when needed."""

    def __init__(self, dims: int, c_in: int, c_out: int, stride: int = 1) -> None:
        super().__init__()
        self.body = nn.Sequential(
            conv(dims, c_in, c_out, 3, stride),
            norm(dims, c_out),
            nn.ReLU(inplace=True),
            conv(dims, c_out, c_out, 3),
            norm(dims, c_out),
        )
        self.skip = (
            nn.Identity()
            if stride == 1 and c_in == c_out
            else nn.Sequential(conv(dims, c_in, c_out, 1, stride), norm(dims, c_out))
        )
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.relu(self.body(x) + self.skip(x))


class ResidualEncoder(nn.Module):
    """Stages of 2 BasicBlocks, each halving the resolution: channels (2C, 4C, 8C) by default."""

    def __init__(self, dims: int, c_in: int, channels: tuple[int, ...]) -> None:
        super().__init__()
        stages = []
        for c_out in channels:
            stages.append(nn.Sequential(ResidualBlock(dims, c_in, c_out, 2), ResidualBlock(dims, c_out, c_out)))
            c_in = c_out
        self.stages = nn.ModuleList(stages)

    def forward(self, x: Tensor) -> list[Tensor]:
        outs = []
        for stage in self.stages:
            x = stage(x)
            outs.append(x)
        return outs


class FPNDecoder(nn.Module):
    """Top-down FPN back to the input resolution. Upsampling goes to the explicit size of the finer level
    (100 -> 50 -> 25 -> 13 does not invert by a factor of 2)."""

    def __init__(self, dims: int, in_channels: tuple[int, ...], out_channels: int) -> None:
        super().__init__()
        self.mode = "bilinear" if dims == 2 else "trilinear"
        self.laterals = nn.ModuleList(conv(dims, c, out_channels, 1, bias=True) for c in in_channels)
        self.out = nn.Sequential(conv(dims, out_channels, out_channels, 3), norm(dims, out_channels), nn.ReLU(True))

    def forward(self, levels: list[Tensor]) -> Tensor:
        """levels: finest first (the input itself, then each encoder stage)."""
        x = self.laterals[-1](levels[-1])
        for lateral, level in zip(reversed(self.laterals[:-1]), reversed(levels[:-1]), strict=True):
            x = lateral(level) + F.interpolate(x, size=level.shape[2:], mode=self.mode, align_corners=False)
        return self.out(x)


class BEVDecoder(nn.Module):
    """`(B, C_in, X, Y[, Z])` -> `(B, C_out, X, Y[, Z])`: encoder (2C, 4C, 8C) + FPN over input + 3 stages."""

    def __init__(self, dims: int, c_in: int, base: int, c_out: int) -> None:
        super().__init__()
        channels = (2 * base, 4 * base, 8 * base)
        self.encoder = ResidualEncoder(dims, c_in, channels)
        self.fpn = FPNDecoder(dims, (c_in, *channels), c_out)

    def forward(self, x: Tensor) -> Tensor:
        return self.fpn([x, *self.encoder(x)])
