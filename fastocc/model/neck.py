"""FPN neck: the backbone's stride-8/16/32 maps aggregated into one stride-16 map F."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["FPNNeck"]


class FPNNeck(nn.Module):
    """Three levels into one stride-16 map: 1x1 laterals on s16 and s32 (s32 upsampled to the s16 size),
    a stride-2 3x3 conv bringing s8 down to s16, summed, then a 3x3 conv + BN + ReLU.

    Input: maps `(B', C_k, H/8, W/8)`, `(B', C_k, H/16, W/16)`, `(B', C_k, H/32, W/32)`.
    Output: `(B', C1, H/16, W/16) float32`.
    """

    def __init__(self, in_channels: tuple[int, int, int], out_channels: int) -> None:
        super().__init__()
        c8, c16, c32 = in_channels
        self.down8 = nn.Conv2d(c8, out_channels, 3, stride=2, padding=1)
        self.lateral16 = nn.Conv2d(c16, out_channels, 1)
        self.lateral32 = nn.Conv2d(c32, out_channels, 1)
        self.out = nn.Sequential(
            nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )

    def forward(self, feats: tuple[Tensor, Tensor, Tensor]) -> Tensor:
        c8, c16, c32 = feats
        size = c16.shape[-2:]
        x = self.lateral16(c16) + F.interpolate(self.lateral32(c32), size=size, mode="bilinear", align_corners=False)
        x = x + self.down8(c8)[..., : size[0], : size[1]]
        return self.out(x)
