"""Test oracles for `occdata.labels.paint`: plain numpy twins of its kernels (nothing in occdata uses
them). The depth buffer by `np.minimum.at`; the occlusion test by shifting the whole buffer."""

from __future__ import annotations

import numpy as np

__all__ = ["depth_buffer_reference", "visible_reference"]


def depth_buffer_reference(cell_u: np.ndarray, cell_v: np.ndarray, depth: np.ndarray, n_u: int,
                           n_v: int) -> np.ndarray:
    """Numpy twin of `depth_buffer`: `(n_v, n_u) float64` least depth per cell, inf where none."""
    out = np.full((n_v, n_u), np.inf)
    np.minimum.at(out, (cell_v, cell_u), depth)
    return out


def visible_reference(cell_u: np.ndarray, cell_v: np.ndarray, depth: np.ndarray, buffer: np.ndarray, radius: int,
                      tolerance: float, tolerance_rel: float) -> np.ndarray:
    """Numpy twin of `visible_points`: the buffer's least value over each cell's neighbourhood (a padded
    buffer shifted by every offset within `radius`), then the tolerance test per point."""
    n_v, n_u = buffer.shape
    pad = np.full((n_v + 2 * radius, n_u + 2 * radius), np.inf)
    pad[radius:radius + n_v, radius:radius + n_u] = buffer
    nearest = np.full(buffer.shape, np.inf)
    for dv in range(2 * radius + 1):
        for du in range(2 * radius + 1):
            nearest = np.minimum(nearest, pad[dv:dv + n_v, du:du + n_u])
    near = nearest[cell_v, cell_u]
    return depth <= near + tolerance + tolerance_rel * near
