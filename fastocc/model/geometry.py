"""Torch-side geometry shared by the view transform and interpolation sampling (docs/design.md#frames-and-names,
#augmentation).

Pixel convention: integer (u, v) are pixel centres. Feature cell (r, c) of a stride-s map covers the
augmented pixels [s c, s c + s) and its centre is the augmented pixel (s c + (s-1)/2, s r + (s-1)/2).
"""

from __future__ import annotations

import torch
from torch import Tensor

from occdata.constants import OccGrid

__all__ = [
    "feature_cell_centres_uv",
    "flat_voxel_index",
    "frustum_points_aug",
    "project_points_to_feature",
    "voxel_centres",
]


def feature_cell_centres_uv(feat_hw: tuple[int, int], stride: int, device: torch.device | None = None) -> Tensor:
    """Augmented-pixel centres of all feature cells, `(h, w, 2) float32` as (u, v)."""
    h, w = feat_hw
    off = (stride - 1) / 2.0
    v = torch.arange(h, dtype=torch.float32, device=device) * stride + off
    u = torch.arange(w, dtype=torch.float32, device=device) * stride + off
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1)


def frustum_points_aug(
    K: Tensor, T_keyego_from_cam: Tensor, img_aug: Tensor, bev_aug: Tensor, uv_img: Tensor, depths: Tensor
) -> Tensor:
    """Lift pixels at given depths into the augmented key-ego frame.

    K `(B, N, 3, 3)`, T_keyego_from_cam `(B, N, 4, 4)`, img_aug `(B, N, 3, 3)`, bev_aug `(B, 4, 4)`,
    uv_img `(h, w, 2)` augmented pixels, depths `(D,)` metres (camera z). Returns `(B, N, D, h, w, 3)`.
    Chain: A^-1 (augmented -> original pixel), K^-1 (ray with z = 1), x depth, T_keyego_from_cam, M.
    """
    uv1 = torch.cat([uv_img, torch.ones_like(uv_img[..., :1])], dim=-1)  # (h, w, 3)
    cam_from_aug = torch.linalg.inv(K) @ torch.linalg.inv(img_aug)  # (B, N, 3, 3)
    rays_cam = torch.einsum("bnij,hwj->bnhwi", cam_from_aug, uv1)
    rays_cam = rays_cam / rays_cam[..., 2:3]  # affine A keeps w = 1; normalise so the ray has z = 1
    points_cam = rays_cam[:, :, None] * depths[None, None, :, None, None, None]  # (B, N, D, h, w, 3)
    T = bev_aug[:, None] @ T_keyego_from_cam  # (B, N, 4, 4) camera -> augmented key ego
    return torch.einsum("bnij,bndhwj->bndhwi", T[..., :3, :3], points_cam) + T[:, :, None, None, None, :3, 3]


def voxel_centres(grid: OccGrid, device: torch.device | None = None) -> Tensor:
    """Voxel centres `(X, Y, Z, 3) float32` in the grid's (augmented key-ego) frame."""
    axes = [
        lo + grid.voxel_size * (torch.arange(n, dtype=torch.float32, device=device) + 0.5)
        for lo, n in zip(grid.lower, grid.shape, strict=True)
    ]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)


def flat_voxel_index(points: Tensor, grid: OccGrid) -> tuple[Tensor, Tensor]:
    """Floor-voxelise points `(..., 3)`: flat index `(...) int64` (x-major: (ix Y + iy) Z + iz) and an
    in-grid mask `(...) bool`. Indices of out-of-grid points are meaningless (mask them)."""
    lower = torch.tensor(grid.lower, dtype=points.dtype, device=points.device)
    idx = torch.floor((points - lower) / grid.voxel_size).long()
    X, Y, Z = grid.shape
    dims = torch.tensor([X, Y, Z], device=points.device)
    inside = ((idx >= 0) & (idx < dims)).all(dim=-1)
    flat = (idx[..., 0] * Y + idx[..., 1]) * Z + idx[..., 2]
    return flat, inside


def project_points_to_feature(
    points_aug: Tensor,
    K: Tensor,
    T_keyego_from_cam: Tensor,
    img_aug: Tensor,
    bev_aug: Tensor,
    input_hw: tuple[int, int],
    stride: int,
    min_depth: float = 0.1,
) -> tuple[Tensor, Tensor]:
    """Project augmented key-ego points `(P, 3)` into every camera's feature map.

    Returns continuous feature coordinates `(B, N, P, 2)` as (x, y) with cell centres at integers, and a
    visibility mask `(B, N, P) bool`: depth > min_depth and the augmented pixel inside [0, W-1] x [0, H-1].
    """
    T_cam_from_aug = torch.linalg.inv(bev_aug[:, None] @ T_keyego_from_cam)  # (B, N, 4, 4)
    points_cam = (
        torch.einsum("bnij,pj->bnpi", T_cam_from_aug[..., :3, :3], points_aug) + T_cam_from_aug[..., None, :3, 3]
    )
    depth = points_cam[..., 2]
    uvw = torch.einsum("bnij,bnpj->bnpi", img_aug @ K, points_cam)
    uv_img = uvw[..., :2] / uvw[..., 2:3].clamp_min(1e-6)
    H, W = input_hw
    visible = (
        (depth > min_depth)
        & (uv_img[..., 0] >= 0)
        & (uv_img[..., 0] <= W - 1)
        & (uv_img[..., 1] >= 0)
        & (uv_img[..., 1] <= H - 1)
    )
    feat_xy = (uv_img - (stride - 1) / 2.0) / stride
    return feat_xy, visible
