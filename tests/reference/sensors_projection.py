"""Test oracles for `occdata.sensors.projection`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

__all__ = ["project_to_cameras_reference"]


def project_to_cameras_reference(
    points_lidar: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    K: np.ndarray,
    sizes: np.ndarray,
    min_depth: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin of `project_to_cameras` (same arithmetic order, same outputs)."""
    p3 = np.asarray(points_lidar[:, :3], dtype=np.float64)
    x, y, z = p3[:, 0], p3[:, 1], p3[:, 2]
    n_cam = K.shape[0]
    uvd = np.zeros((n_cam, len(p3), 3), dtype=np.float32)
    counts = np.zeros(n_cam, dtype=np.int64)
    for c in range(n_cam):
        T, k = T_cam_from_lidar[c], K[c]
        p = np.empty((3, 4))
        for r in range(3):
            p[r] = k[r, 0] * T[0] + k[r, 1] * T[1] + k[r, 2] * T[2]
        zc = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / (p[2, 0] * x + p[2, 1] * y + p[2, 2] * z + p[2, 3])
            u = (p[0, 0] * x + p[0, 1] * y + p[0, 2] * z + p[0, 3]) * inv
            v = (p[1, 0] * x + p[1, 1] * y + p[1, 2] * z + p[1, 3]) * inv
            keep = (zc > min_depth) & (u >= 0) & (u < sizes[c, 0]) & (v >= 0) & (v < sizes[c, 1])
        m = int(keep.sum())
        uvd[c, :m] = np.stack([u[keep], v[keep], zc[keep]], axis=1)
        counts[c] = m
    return uvd, counts
