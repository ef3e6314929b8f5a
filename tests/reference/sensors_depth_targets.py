"""Test oracles for `occdata.sensors.depth_targets`: plain numpy twins of its kernels, which the tests compare the
kernels against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.sensors.depth_targets import _transform_round

__all__ = ["rasterise_depth_reference", "min_pool_depth_reference", "depth_target_reference"]


def rasterise_depth_reference(
    uvd: np.ndarray, A: np.ndarray, height: int, width: int, d_min: float, d_max: float
) -> np.ndarray:
    """Numpy twin of `rasterise_depth`."""
    x, y, d = _transform_round(uvd, A)
    keep = (d >= d_min) & (d < d_max) & (x >= 0) & (x < width) & (y >= 0) & (y < height)
    flat = y[keep].astype(np.int64) * width + x[keep].astype(np.int64)
    best = np.full(height * width, np.inf, dtype=np.float32)
    np.minimum.at(best, flat, d[keep])
    best[np.isinf(best)] = 0
    return best.reshape(height, width)


def min_pool_depth_reference(depth: np.ndarray, stride: int) -> np.ndarray:
    """Numpy twin of `min_pool_depth`."""
    h, w = depth.shape[0] // stride, depth.shape[1] // stride
    patches = depth[: h * stride, : w * stride].reshape(h, stride, w, stride).astype(np.float32)
    patches = np.where(patches > 0, patches, np.inf).min(axis=(1, 3))
    return np.where(np.isinf(patches), 0, patches).astype(np.float32)


def depth_target_reference(
    uvd: np.ndarray, A: np.ndarray, height: int, width: int, stride: int, d_min: float, d_max: float
) -> np.ndarray:
    """Numpy twin of `depth_target` (the two-step definition)."""
    return min_pool_depth_reference(rasterise_depth_reference(uvd, A, height, width, d_min, d_max), stride)
