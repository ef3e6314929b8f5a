"""The voxel ray stepper: 3D DDA (Amanatides & Woo) along a segment through a regular voxel grid.

Used by the visibility masks (camera occlusion counts, LiDAR ray masks) that the store, the labels
generator and the synthetic world share. A grid is `(X, Y, Z)` voxels of `voxel_size` metres with
lower corner `lower (3,) float64`; segments are `a -> b (3,) float64` in the grid's frame.

RayIoU (`occdata.eval.rayiou`) keeps its own caster on purpose: the metric is defined by the
reference code's arithmetic (float32 voxel-unit origins, unit directions, its tie order and step
cap), and it is checked equal to that code; this stepper's metric-unit arithmetic would move
boundary hits.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["segment_advance", "segment_setup"]


@njit(cache=True)
def segment_setup(
    a: np.ndarray, b: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
    idx: np.ndarray, step: np.ndarray, t_next: np.ndarray, t_delta: np.ndarray,
) -> tuple[bool, float]:
    """Clip segment a->b (param t in [0, 1]) to the grid; fill the start voxel `idx`, `step`, next
    boundary `t_next` and `t_delta` (3,) scratch arrays; returns (non-empty, t at the segment end)."""
    d = b - a
    t0, t1 = 0.0, 1.0
    for k in range(3):
        lo = lower[k]
        hi = lower[k] + shape[k] * voxel_size
        if abs(d[k]) < 1e-15:
            if a[k] < lo or a[k] >= hi:
                t0, t1 = 1.0, 0.0
        else:
            ta = (lo - a[k]) / d[k]
            tb = (hi - a[k]) / d[k]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if t0 > t1:
        return False, t1
    for k in range(3):
        step[k] = 0
        t_next[k] = np.inf
        t_delta[k] = np.inf
        p = a[k] + t0 * d[k]
        i = int(np.floor((p - lower[k]) / voxel_size))
        i = min(max(i, 0), shape[k] - 1)
        idx[k] = i
        if d[k] > 0.0:
            step[k] = 1
            t_next[k] = (lower[k] + (i + 1) * voxel_size - a[k]) / d[k]
            t_delta[k] = voxel_size / d[k]
        elif d[k] < 0.0:
            step[k] = -1
            t_next[k] = (lower[k] + i * voxel_size - a[k]) / d[k]
            t_delta[k] = -voxel_size / d[k]
    return True, t1


@njit(cache=True)
def segment_advance(
    idx: np.ndarray, step: np.ndarray, t_next: np.ndarray, t_delta: np.ndarray, shape: np.ndarray
) -> float:
    """Step into the next voxel along the ray; returns the entry t of the new voxel (inf if it left the grid)."""
    k = 0
    if t_next[1] < t_next[k]:
        k = 1
    if t_next[2] < t_next[k]:
        k = 2
    t_enter = t_next[k]
    idx[k] += step[k]
    t_next[k] += t_delta[k]
    if idx[k] < 0 or idx[k] >= shape[k]:
        return np.inf
    return t_enter
