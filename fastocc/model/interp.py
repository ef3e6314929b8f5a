"""Interpolation sampling: image features at the fine voxel centres, averaged over cameras (DESIGN §7.4)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occdata.constants import OccGrid

from .geometry import project_points_to_feature, voxel_centres
from .inputs import SceneInputs
from .view_transform import CalibrationCache

__all__ = ["InterpolationSampler", "SamplingIndex"]


@dataclass(frozen=True)
class SamplingIndex:
    """A sparse (B*V) x (B*N*h*w) matrix in CSR-like bags for `embedding_bag`.

    rows: `(E,) int64` into the flattened channels-last feature table `(B*N*h*w, C)`.
    weights: `(E,) float32` bilinear weight / number of cameras that see the voxel.
    offsets: `(B*V,) int64` start of each voxel's entries (voxels seen by no camera have none -> 0).
    """

    rows: Tensor
    weights: Tensor
    offsets: Tensor


class InterpolationSampler(nn.Module):
    """Bilinearly sample `(B*N, C, h, w)` features at every fine voxel centre (projected with M^-1,
    T_keyego_from_cam^-1, K, A) and average over the cameras that see the voxel (0 where none).

    The projection is cached like the LSS indices. The sampling itself is one `embedding_bag`
    (a sparse-dense product), linear in the features, so a 1x1 conv may be applied before it.
    Output: `(B, X, Y, Z, C) float32`, channels last.
    """

    def __init__(self, grid: OccGrid, input_hw: tuple[int, int], stride: int) -> None:
        super().__init__()
        self.grid = grid
        self.input_hw = input_hw
        self.stride = stride
        self._cache: CalibrationCache[SamplingIndex] = CalibrationCache()

    def clear_cache(self) -> None:
        self._cache.clear()

    def index(self, inputs: SceneInputs, feat_hw: tuple[int, int]) -> SamplingIndex:
        return self._cache.get(inputs, lambda device: self._build(inputs, feat_hw, device))

    def _build(self, inputs: SceneInputs, feat_hw: tuple[int, int], device: torch.device) -> SamplingIndex:
        h, w = feat_hw
        N = inputs.num_cams
        points_aug = voxel_centres(self.grid, device).reshape(-1, 3)
        V = points_aug.shape[0]
        feat_xy, visible = project_points_to_feature(
            points_aug, inputs.K, inputs.T_keyego_from_cam, inputs.img_aug, inputs.bev_aug, self.input_hw, self.stride
        )  # (B, N, V, 2), (B, N, V)
        # pairs ordered by (b, v, n) so the entries come out grouped by voxel (bag) without a sort
        b, v, n = torch.nonzero(visible.permute(0, 2, 1), as_tuple=True)
        xy = feat_xy[b, n, v]
        per_voxel = visible.sum(dim=1).reshape(-1)  # (B*V,) cameras that see each voxel
        inv_count = 1.0 / per_voxel[b * V + v].float()
        x0 = torch.floor(xy[:, 0])
        y0 = torch.floor(xy[:, 1])
        fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
        x0, y0 = x0.long(), y0.long()
        xs = torch.stack([x0, x0 + 1, x0, x0 + 1], dim=1)  # (P, 4) bilinear corners
        ys = torch.stack([y0, y0, y0 + 1, y0 + 1], dim=1)
        wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=1)
        inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)  # zero padding: outside corners weigh 0
        rows = ((b * N + n)[:, None] * h + ys.clamp(0, h - 1)) * w + xs.clamp(0, w - 1)
        weights = torch.where(inside, wts * inv_count[:, None], torch.zeros_like(wts))
        per_bag = 4 * per_voxel
        offsets = torch.cumsum(per_bag, 0) - per_bag
        return SamplingIndex(rows=rows.reshape(-1), weights=weights.reshape(-1), offsets=offsets)

    def forward(self, feat: Tensor, inputs: SceneInputs) -> Tensor:
        """feat `(B*N, C, h, w)` -> P `(B, X, Y, Z, C)` (channels last)."""
        _, C, h, w = feat.shape
        index = self.index(inputs, (h, w))
        table = feat.permute(0, 2, 3, 1).reshape(-1, C)
        out = F.embedding_bag(index.rows, table, index.offsets, mode="sum", per_sample_weights=index.weights)
        return out.view(inputs.batch_size, *self.grid.shape, C)
