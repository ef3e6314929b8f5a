"""Test oracles for `occdata.synth.labels`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.synth.labels import _OVERLAP_EPS

__all__ = ["voxelize_primitives_reference"]


def voxelize_primitives_reference(
    semantics: np.ndarray, params: np.ndarray, cls: np.ndarray, priority: np.ndarray, lower: np.ndarray,
    voxel_size: float,
) -> np.ndarray:
    """Numpy twin of `voxelize_primitives` (vectorised over all voxels, per primitive)."""
    out = semantics.copy()
    X, Y, Z = semantics.shape
    h = 0.5 * voxel_size
    e = _OVERLAP_EPS
    qx, qy, qz0 = np.meshgrid(lower[0] + (np.arange(X) + 0.5) * voxel_size,
                              lower[1] + (np.arange(Y) + 0.5) * voxel_size,
                              lower[2] + np.arange(Z) * voxel_size, indexing="ij")
    for p, c in zip(params, cls, strict=True):
        zok = (p[8] >= qz0 - e) & (p[7] <= qz0 + 2 * h + e)
        rx, ry = qx - p[1], qy - p[2]
        if p[0] == 0.0:
            co, si = p[3], p[4]
            ac, as_ = abs(co), abs(si)
            ok = (np.abs(rx) <= h + ac * p[5] + as_ * p[6] + e) & (np.abs(ry) <= h + as_ * p[5] + ac * p[6] + e)
            ok &= np.abs(co * rx + si * ry) <= p[5] + h * (ac + as_) + e
            ok &= np.abs(-si * rx + co * ry) <= p[6] + h * (ac + as_) + e
        else:
            ddx = np.maximum(np.abs(rx) - h, 0.0)
            ddy = np.maximum(np.abs(ry) - h, 0.0)
            ok = ddx**2 + ddy**2 <= (p[5] + e) ** 2
        ok &= zok & (priority[c] > priority[out])
        out[ok] = c
    return out
