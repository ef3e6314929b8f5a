"""Test oracles for `occdata.synth.gridtruth`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.synth.labels import _OVERLAP_EPS

__all__ = ["voxelize_tilted_reference"]


def voxelize_tilted_reference(semantics: np.ndarray, params: np.ndarray, cls: np.ndarray, priority: np.ndarray,
                              R_level_from_grid: np.ndarray, lower: np.ndarray, voxel_size: float) -> np.ndarray:
    """Numpy twin of `voxelize_tilted` (every voxel against each primitive, vectorised)."""
    out = semantics.copy()
    R, h, e = np.asarray(R_level_from_grid, np.float64), 0.5 * voxel_size, _OVERLAP_EPS
    ex, ey, ez = h * np.abs(R).sum(1)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in semantics.shape], indexing="ij"), -1)
    q = (np.asarray(lower) + (idx + 0.5) * voxel_size) @ R.T
    qx, qy, qz = q[..., 0], q[..., 1], q[..., 2]
    for p, c in zip(params, cls, strict=True):
        ok = (p[8] >= qz - ez - e) & (p[7] <= qz + ez + e)
        rx, ry = qx - p[1], qy - p[2]
        if p[0] == 0.0:
            ac, as_ = abs(p[3]), abs(p[4])
            ok &= (np.abs(rx) <= ex + ac * p[5] + as_ * p[6] + e) & (np.abs(ry) <= ey + as_ * p[5] + ac * p[6] + e)
            ok &= np.abs(p[3] * rx + p[4] * ry) <= p[5] + ac * ex + as_ * ey + e
            ok &= np.abs(-p[4] * rx + p[3] * ry) <= p[6] + as_ * ex + ac * ey + e
        else:
            ok &= np.maximum(np.abs(rx) - ex, 0) ** 2 + np.maximum(np.abs(ry) - ey, 0) ** 2 <= (p[5] + e) ** 2
        ok &= priority[c] > priority[out]
        out[ok] = c
    return out
