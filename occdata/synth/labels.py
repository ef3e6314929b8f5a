"""Occ3D-style voxel labels of the synthetic world in the key-ego frame.

A voxel takes the class of the highest-priority primitive whose closed volume touches it (so every
surface point, hence every LiDAR hit, lies in an occupied voxel); the ground plane z = 0 fills the
voxel layer containing it with the ground raster's class. Everything else is free (17).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occdata.constants import FREE_LABEL, GRID, NUM_CLASSES, OccGrid
from occdata.synth.world import GroundRaster, Primitives

__all__ = [
    "CLASS_PRIORITY",
    "ground_layer",
    "primitives_to_frame",
    "voxelize_primitives",
    "world_semantics",
]

# Higher wins where primitives share a voxel: small dynamic objects first, ground last, free lowest.
_ORDER = (7, 2, 6, 8, 1, 4, 10, 3, 9, 5, 0, 16, 15, 11, 12, 13, 14, 17)
CLASS_PRIORITY = np.zeros(NUM_CLASSES, np.int32)
for _rank, _c in enumerate(_ORDER):
    CLASS_PRIORITY[_c] = len(_ORDER) - _rank
_OVERLAP_EPS = 1e-4  # m; boundary slack so surface points on voxel faces still count


def primitives_to_frame(params_global: np.ndarray, T_global_from_frame: np.ndarray) -> np.ndarray:
    """Express primitives `(P, 9)` in a frame related to global by a yaw-only rigid transform
    (ego frames: z = 0, no roll/pitch). Returns `(P, 9) float64`."""
    c, s = T_global_from_frame[0, 0], T_global_from_frame[1, 0]
    tx, ty = T_global_from_frame[0, 3], T_global_from_frame[1, 3]
    p = params_global.copy()
    dx, dy = params_global[:, 1] - tx, params_global[:, 2] - ty
    p[:, 1] = c * dx + s * dy
    p[:, 2] = -s * dx + c * dy
    p[:, 3] = params_global[:, 3] * c + params_global[:, 4] * s
    p[:, 4] = params_global[:, 4] * c - params_global[:, 3] * s
    p[:, 7:9] -= T_global_from_frame[2, 3]
    return p


@njit(cache=True)
def _overlaps(p: np.ndarray, qx: float, qy: float, qz0: float, h: float) -> bool:
    """Whether primitive `p (9,)` touches the voxel with xy centre (qx, qy), z in [qz0, qz0 + 2h]."""
    e = _OVERLAP_EPS
    if p[8] < qz0 - e or p[7] > qz0 + 2.0 * h + e:
        return False
    rx, ry = qx - p[1], qy - p[2]
    if p[0] == 0.0:
        c, s = p[3], p[4]
        ac, as_ = abs(c), abs(s)
        if abs(rx) > h + ac * p[5] + as_ * p[6] + e:
            return False
        if abs(ry) > h + as_ * p[5] + ac * p[6] + e:
            return False
        if abs(c * rx + s * ry) > p[5] + h * (ac + as_) + e:
            return False
        return abs(-s * rx + c * ry) <= p[6] + h * (ac + as_) + e
    ddx = max(abs(rx) - h, 0.0)
    ddy = max(abs(ry) - h, 0.0)
    return ddx * ddx + ddy * ddy <= (p[5] + e) * (p[5] + e)


@njit(cache=True, parallel=True)
def voxelize_primitives(
    semantics: np.ndarray, params: np.ndarray, cls: np.ndarray, priority: np.ndarray, lower: np.ndarray,
    voxel_size: float,
) -> np.ndarray:
    """Paint primitives `params (P, 9) float64` (grid frame) with classes `cls (P,) int32` over a copy
    of `semantics (X, Y, Z) uint8`; a voxel keeps the class with the highest `priority (18,) int32`.
    Returns `(X, Y, Z) uint8`."""
    X, Y, Z = semantics.shape
    out = semantics.copy()
    h = 0.5 * voxel_size
    # Parallel over x slabs: each thread owns its voxels, primitives are scanned in order.
    for i in prange(X):
        qx = lower[0] + (i + 0.5) * voxel_size
        for n in range(params.shape[0]):
            p = params[n]
            ex = abs(p[3]) * p[5] + abs(p[4]) * p[6] if p[0] == 0.0 else p[5]
            if abs(qx - p[1]) > ex + h + _OVERLAP_EPS:
                continue
            ey = abs(p[4]) * p[5] + abs(p[3]) * p[6] if p[0] == 0.0 else p[5]
            j0 = max(int(np.floor((p[2] - ey - lower[1]) / voxel_size)) - 1, 0)
            j1 = min(int(np.floor((p[2] + ey - lower[1]) / voxel_size)) + 1, Y - 1)
            k0 = max(int(np.floor((p[7] - lower[2]) / voxel_size)) - 1, 0)
            k1 = min(int(np.floor((p[8] - lower[2]) / voxel_size)) + 1, Z - 1)
            c = cls[n]
            for j in range(j0, j1 + 1):
                qy = lower[1] + (j + 0.5) * voxel_size
                for k in range(k0, k1 + 1):
                    if priority[c] <= priority[out[i, j, k]]:
                        continue
                    if _overlaps(p, qx, qy, lower[2] + k * voxel_size, h):
                        out[i, j, k] = c
    return out


def ground_layer(ground: GroundRaster, T_global_from_keyego: np.ndarray, grid: OccGrid = GRID) -> np.ndarray:
    """`(X, Y, Z) uint8` semantics with only the ground: the voxel layer containing z = 0 gets the
    ground class at each voxel centre (looked up in global); the rest is free."""
    X, Y, Z = grid.shape
    sem = np.full((X, Y, Z), FREE_LABEL, np.uint8)
    k = int(np.floor((0.0 - T_global_from_keyego[2, 3] - grid.lower[2]) / grid.voxel_size))
    if 0 <= k < Z:
        centres = grid.voxel_centers()[:, :, k, :2].reshape(-1, 2).astype(np.float64)
        xy_g = centres @ T_global_from_keyego[:2, :2].T + T_global_from_keyego[:2, 3]
        sem[:, :, k] = ground.lookup(xy_g).reshape(X, Y)
    return sem


def world_semantics(
    ground: GroundRaster, prims: Primitives, T_global_from_keyego: np.ndarray, grid: OccGrid = GRID
) -> np.ndarray:
    """Semantics `(X, Y, Z) uint8` of the world (primitives at the key timestamp) in key ego."""
    sem = ground_layer(ground, T_global_from_keyego, grid)
    params = primitives_to_frame(prims.params, T_global_from_keyego)
    lower = np.asarray(grid.lower, np.float64)
    return voxelize_primitives(sem, params, prims.cls, CLASS_PRIORITY, lower, grid.voxel_size)
