"""2D -> 3D view transform: depth net (88-bin softmax + context) and LSS voxel pooling (docs/design.md#the-network)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import torch
from torch import Tensor, nn

from occdata.constants import OccGrid

from .geometry import feature_cell_centres_uv, flat_voxel_index, frustum_points_aug
from .inputs import SceneInputs

T = TypeVar("T")

__all__ = ["DepthNet", "LSSPooling", "PoolingIndex", "lss_pool"]


class DepthNet(nn.Module):
    """Per feature pixel: a softmax over D depth bins and C2 context channels.

    Input `(B', C1, h, w)`; returns depth `(B', D, h, w)` (sums to 1 over D) and context `(B', C2, h, w)`.
    """

    def __init__(self, in_channels: int, context_channels: int, num_bins: int) -> None:
        super().__init__()
        self.num_bins = num_bins
        self.reduce = nn.Sequential(
            nn.Conv2d(in_channels, in_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(in_channels),
            nn.ReLU(inplace=True),
        )
        self.out = nn.Conv2d(in_channels, num_bins + context_channels, 1)

    def forward(self, feat: Tensor) -> tuple[Tensor, Tensor]:
        x = self.out(self.reduce(feat))
        return x[:, : self.num_bins].softmax(dim=1), x[:, self.num_bins :]


@dataclass(frozen=True)
class PoolingIndex:
    """Frustum points that land in the grid.

    point_idx: `(P,) int64` into the flattened `(B*N, D, h, w)` frustum.
    voxel_idx: `(P,) int64` into the flattened `(B, X, Y, Z)` grid.
    """

    point_idx: Tensor
    voxel_idx: Tensor


def lss_pool(
    depth: Tensor, context: Tensor, index: PoolingIndex, batch: int, grid_shape: tuple[int, int, int]
) -> Tensor:
    """Sum depth x context of every frustum point into its voxel.

    depth `(B*N, D, h, w)`, context `(B*N, C, h, w)` -> V_B `(B, C, X, Y, Z) float32`.
    """
    C = context.shape[1]
    # (B*N, D, h, w, C): the outer product, channels last so each frustum point is one row
    feats = depth.unsqueeze(-1) * context.permute(0, 2, 3, 1).unsqueeze(1)
    rows = feats.reshape(-1, C).index_select(0, index.point_idx)
    X, Y, Z = grid_shape
    pooled = feats.new_zeros(batch * X * Y * Z, C).index_add_(0, index.voxel_idx, rows)
    return pooled.view(batch, X, Y, Z, C).permute(0, 4, 1, 2, 3)


def calibration_key(inputs: SceneInputs) -> Tensor:
    """All matrices the geometry depends on, flattened; equal keys -> identical indices."""
    parts = [inputs.K, inputs.T_keyego_from_cam, inputs.img_aug, inputs.bev_aug]
    return torch.cat([p.reshape(-1).float() for p in parts])


class CalibrationCache(Generic[T]):
    """One value (e.g. a geometry index) kept while the calibration / augmentation matrices stay equal."""

    def __init__(self) -> None:
        self._entry: tuple[Tensor, T] | None = None

    def clear(self) -> None:
        self._entry = None

    def get(self, inputs: SceneInputs, build: Callable[[torch.device], T]) -> T:
        """The cached value for these inputs, or `build(device)` (run without autograd) on a change."""
        key = calibration_key(inputs)
        if self._entry is not None and self._entry[0].shape == key.shape and torch.equal(self._entry[0], key):
            return self._entry[1]
        with torch.no_grad():
            value = build(key.device)
        self._entry = (key, value)
        return value


class LSSPooling(nn.Module):
    """Voxel pooling into the coarse grid with cached indices.

    The flat voxel index of every frustum point is recomputed only when the calibration / augmentation
    matrices change (inference with a fixed rig hits the cache every frame).
    """

    def __init__(self, grid: OccGrid, depth_centres: list[float], input_hw: tuple[int, int], stride: int) -> None:
        super().__init__()
        self.grid = grid
        self.input_hw = input_hw
        self.stride = stride
        self.register_buffer("depth_centres", torch.tensor(depth_centres, dtype=torch.float32), persistent=False)
        self._cache: CalibrationCache[PoolingIndex] = CalibrationCache()

    def clear_cache(self) -> None:
        self._cache.clear()

    def index(self, inputs: SceneInputs, feat_hw: tuple[int, int]) -> PoolingIndex:
        def build(device: torch.device) -> PoolingIndex:
            uv_img = feature_cell_centres_uv(feat_hw, self.stride, device)
            points_aug = frustum_points_aug(
                inputs.K, inputs.T_keyego_from_cam, inputs.img_aug, inputs.bev_aug, uv_img, self.depth_centres
            )  # (B, N, D, h, w, 3)
            flat, inside = flat_voxel_index(points_aug, self.grid)
            B = points_aug.shape[0]
            flat = flat + torch.arange(B, device=flat.device).view(B, 1, 1, 1, 1) * self.grid.shape[0] * (
                self.grid.shape[1] * self.grid.shape[2]
            )
            point_idx = torch.nonzero(inside.reshape(-1)).squeeze(1)
            return PoolingIndex(point_idx=point_idx, voxel_idx=flat.reshape(-1)[point_idx])

        return self._cache.get(inputs, build)

    def forward(self, depth: Tensor, context: Tensor, inputs: SceneInputs) -> Tensor:
        """depth `(B*N, D, h, w)`, context `(B*N, C2, h, w)` -> V_B `(B, C2, 100, 100, 8)`."""
        index = self.index(inputs, (depth.shape[2], depth.shape[3]))
        return lss_pool(depth, context, index, inputs.batch_size, self.grid.shape)
