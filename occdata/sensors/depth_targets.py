"""Depth targets at the network input from stored LiDAR (u, v, depth) points (docs/design.md#the-store-layout).
No torch.

Points are stored in ORIGINAL-image pixels; at load time they are moved by the image-augmentation
matrix A (3x3, original pixel -> augmented pixel), rounded to the nearest pixel (floor(x + 0.5), the
same in numba and numpy), kept when 0 <= u < W, 0 <= v < H and d_min <= d < d_max, and the NEAREST
point wins per pixel. The per-pixel map is then min-pooled to the feature stride (minimum positive
depth per stride x stride patch; 0 = no target).

Because the min over a patch of per-pixel minima is the min over all points in the patch, the fused
kernel `depth_target` never materialises the full-resolution map; `rasterise_depth` + `min_pool_depth`
are the two-step definition and the tests check that both agree.

Each numba kernel has a plain numpy twin (`*_reference`, tests/reference/) checked for equality on random inputs.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "DEPTH_MAX",
    "DEPTH_MIN",
    "depth_target",
    "min_pool_depth",
    "rasterise_depth",
]

DEPTH_MIN, DEPTH_MAX = 1.0, 45.0  # the depth-bin range [1, 45) m of docs/design.md#the-store-layout


@numba.njit(cache=True, nogil=True, inline="always")
def _augmented_pixel(A: np.ndarray, u: float, v: float) -> tuple[float, float]:
    """Original pixel (u, v) -> nearest augmented pixel (floor(x + 0.5)) through the 3x3 matrix A."""
    w = A[2, 0] * u + A[2, 1] * v + A[2, 2]
    x = np.floor((A[0, 0] * u + A[0, 1] * v + A[0, 2]) / w + 0.5)
    y = np.floor((A[1, 0] * u + A[1, 1] * v + A[1, 2]) / w + 0.5)
    return x, y


@numba.njit(cache=True, nogil=True)
def rasterise_depth(
    uvd: np.ndarray, A: np.ndarray, height: int, width: int, d_min: float, d_max: float
) -> np.ndarray:
    """Nearest depth per pixel of the augmented image.

    uvd: `(M, 3) float32` (u, v, depth), u/v in original-image pixels. A: `(3, 3) float64` original
    pixel -> augmented pixel. Returns `(height, width) float32`, 0 where no point lands.
    """
    out = np.zeros((height, width), dtype=np.float32)
    for i in range(uvd.shape[0]):
        d = uvd[i, 2]
        if not (d >= d_min and d < d_max):
            continue
        x, y = _augmented_pixel(A, np.float64(uvd[i, 0]), np.float64(uvd[i, 1]))
        if x < 0 or x >= width or y < 0 or y >= height:
            continue
        xi, yi = int(x), int(y)
        cur = out[yi, xi]
        if cur == 0 or d < cur:
            out[yi, xi] = d
    return out


def _transform_round(uvd: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uv1 = np.concatenate([uvd[:, :2].astype(np.float64), np.ones((len(uvd), 1))], axis=1)
    p = uv1 @ np.asarray(A, dtype=np.float64).T
    x = np.floor(p[:, 0] / p[:, 2] + 0.5)
    y = np.floor(p[:, 1] / p[:, 2] + 0.5)
    return x, y, uvd[:, 2].astype(np.float32)


@numba.njit(cache=True, nogil=True)
def min_pool_depth(depth: np.ndarray, stride: int) -> np.ndarray:
    """`(H, W) float32` -> `(H // stride, W // stride) float32`: min positive depth per patch, 0 if none.

    H and W must be multiples of stride.
    """
    h, w = depth.shape[0] // stride, depth.shape[1] // stride
    out = np.zeros((h, w), dtype=np.float32)
    for y in range(h * stride):
        for x in range(w * stride):
            d = depth[y, x]
            if d > 0:
                cur = out[y // stride, x // stride]
                if cur == 0 or d < cur:
                    out[y // stride, x // stride] = d
    return out


@numba.njit(cache=True, nogil=True)
def depth_target(
    uvd: np.ndarray, A: np.ndarray, height: int, width: int, stride: int, d_min: float, d_max: float
) -> np.ndarray:
    """Fused `min_pool_depth(rasterise_depth(...), stride)`: `(height // stride, width // stride) float32`."""
    h, w = height // stride, width // stride
    out = np.zeros((h, w), dtype=np.float32)
    for i in range(uvd.shape[0]):
        d = uvd[i, 2]
        if not (d >= d_min and d < d_max):
            continue
        x, y = _augmented_pixel(A, np.float64(uvd[i, 0]), np.float64(uvd[i, 1]))
        if x < 0 or x >= width or y < 0 or y >= height:
            continue
        yi, xi = int(y) // stride, int(x) // stride
        if yi >= h or xi >= w:
            continue
        cur = out[yi, xi]
        if cur == 0 or d < cur:
            out[yi, xi] = d
    return out
