"""The synthetic world's truth on any label grid (`occdata.formats.gridspec.GridSpec`), in the grid's own frame.

`world_semantics` (occdata.synth.labels) voxelises the world in a frame related to global by a yaw
alone, the key ego of the Occ3D grid. A LiDAR-frame grid (SurroundOcc, OpenOccupancy) is tilted
against the road: the rig's LIDAR_TOP (nuScenes' calibration) leans 1.4 deg, which moves a voxel
1.2 m up or down at 50 m, so its voxels are not boxes of the yaw-only frame. Here each voxel centre
is taken into the "level" frame (the grid's origin and heading, z up) and tested against the
primitives there with the voxel's level-frame bounding box: the same rule as `world_semantics` (a voxel takes the
highest-priority primitive whose closed volume touches it; the ground plane fills what touches
z = 0), exact for a level grid (tested: equal to `world_semantics` on the Occ3D grid and on a 0.2 m
one) and, for a tilted grid, a superset by at most the bounding box's growth, `h * (sum |R| - 1)`
per side: 0.2 / 0.6 / 0.7 cm in x / y / z for SurroundOcc's 0.5 m voxels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from occdata.constants import FREE_LABEL, OccGrid
from occdata.synth.labels import _OVERLAP_EPS, CLASS_PRIORITY, primitives_to_frame
from occdata.synth.world import GroundRaster, Primitives

__all__ = ["grid_semantics", "level_frame", "voxelize_tilted"]


def level_frame(T_global_from_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(T_global_from_level (4, 4), R_level_from_grid (3, 3))`: the level frame shares the grid's
    origin and the heading of its x axis, with z up (global's); both float64."""
    R = T_global_from_grid[:3, :3]
    if abs(R[2, 2] - 1.0) < 1e-12:  # already level (an ego frame): itself, and no rounding on the way
        return np.array(T_global_from_grid, np.float64), np.eye(3)
    n = math.hypot(R[0, 0], R[1, 0])  # the x axis's heading, normalised: a level frame keeps its own R
    c, s = R[0, 0] / n, R[1, 0] / n
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = T_global_from_grid[:3, 3]
    return T, T[:3, :3].T @ R


@njit(cache=True)
def _touches(p: np.ndarray, qx: float, qy: float, qz: float, ex: float, ey: float, ez: float) -> bool:
    """Whether primitive `p (9,)` (level frame) touches the box centred at (qx, qy, qz) with half
    extents (ex, ey, ez); `occdata.synth.labels._overlaps` with a box that need not be a cube."""
    e = _OVERLAP_EPS
    if p[8] < qz - ez - e or p[7] > qz + ez + e:
        return False
    rx, ry = qx - p[1], qy - p[2]
    if p[0] == 0.0:
        ac, as_ = abs(p[3]), abs(p[4])
        if abs(rx) > ex + ac * p[5] + as_ * p[6] + e or abs(ry) > ey + as_ * p[5] + ac * p[6] + e:
            return False
        if abs(p[3] * rx + p[4] * ry) > p[5] + ac * ex + as_ * ey + e:
            return False
        return abs(-p[4] * rx + p[3] * ry) <= p[6] + as_ * ex + ac * ey + e
    ddx, ddy = max(abs(rx) - ex, 0.0), max(abs(ry) - ey, 0.0)
    return ddx * ddx + ddy * ddy <= (p[5] + e) * (p[5] + e)


def _index_ranges(params: np.ndarray, R: np.ndarray, lower: np.ndarray, voxel_size: float,
                  shape: tuple[int, int, int]) -> np.ndarray:
    """`(P, 6) int64` [i0, i1, j0, j1, k0, k1] (inclusive, clipped): the grid voxels a primitive's
    level-frame bounding box can reach, one voxel of margin."""
    ex = np.where(params[:, 0] == 0.0, np.abs(params[:, 3]) * params[:, 5] + np.abs(params[:, 4]) * params[:, 6],
                  params[:, 5])
    ey = np.where(params[:, 0] == 0.0, np.abs(params[:, 4]) * params[:, 5] + np.abs(params[:, 3]) * params[:, 6],
                  params[:, 5])
    lo_l = np.stack([params[:, 1] - ex, params[:, 2] - ey, params[:, 7]], 1)
    hi_l = np.stack([params[:, 1] + ex, params[:, 2] + ey, params[:, 8]], 1)
    centre, half = (lo_l + hi_l) / 2, (hi_l - lo_l) / 2
    c_grid, h_grid = centre @ R, half @ np.abs(R)  # R: level_from_grid, so grid = R^T level
    lo = np.floor((c_grid - h_grid - lower) / voxel_size).astype(np.int64) - 1
    hi = np.floor((c_grid + h_grid - lower) / voxel_size).astype(np.int64) + 1
    top = np.array(shape, np.int64) - 1
    lo, hi = np.clip(lo, 0, top), np.clip(hi, -1, top)
    return np.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1], lo[:, 2], hi[:, 2]], 1)


@njit(cache=True, parallel=True)
def _paint(out: np.ndarray, params: np.ndarray, cls: np.ndarray, priority: np.ndarray, ranges: np.ndarray,
           R: np.ndarray, lower: np.ndarray, voxel_size: float) -> None:
    h = 0.5 * voxel_size
    ex = h * (abs(R[0, 0]) + abs(R[0, 1]) + abs(R[0, 2]))
    ey = h * (abs(R[1, 0]) + abs(R[1, 1]) + abs(R[1, 2]))
    ez = h * (abs(R[2, 0]) + abs(R[2, 1]) + abs(R[2, 2]))
    for i in prange(out.shape[0]):  # x slabs: each thread owns its voxels, primitives in order
        gx = lower[0] + (i + 0.5) * voxel_size
        for n in range(params.shape[0]):
            if i < ranges[n, 0] or i > ranges[n, 1]:
                continue
            c = cls[n]
            for j in range(ranges[n, 2], ranges[n, 3] + 1):
                gy = lower[1] + (j + 0.5) * voxel_size
                for k in range(ranges[n, 4], ranges[n, 5] + 1):
                    if priority[c] <= priority[out[i, j, k]]:
                        continue
                    gz = lower[2] + (k + 0.5) * voxel_size
                    qx = R[0, 0] * gx + R[0, 1] * gy + R[0, 2] * gz
                    qy = R[1, 0] * gx + R[1, 1] * gy + R[1, 2] * gz
                    qz = R[2, 0] * gx + R[2, 1] * gy + R[2, 2] * gz
                    if _touches(params[n], qx, qy, qz, ex, ey, ez):
                        out[i, j, k] = c


def voxelize_tilted(semantics: np.ndarray, params: np.ndarray, cls: np.ndarray, priority: np.ndarray,
                    R_level_from_grid: np.ndarray, lower: np.ndarray, voxel_size: float) -> np.ndarray:
    """Paint primitives `params (P, 9) float64` (level frame) with classes `cls (P,) int32` over a
    copy of `semantics (X, Y, Z) uint8` (grid frame, `lower (3,)`); a voxel keeps the class of the
    highest `priority (18,) int32`. Returns `(X, Y, Z) uint8`."""
    R = np.ascontiguousarray(R_level_from_grid, np.float64)
    lower = np.asarray(lower, np.float64)
    out = semantics.copy()
    if len(params):
        ranges = _index_ranges(params, R, lower, voxel_size, semantics.shape)
        _paint(out, params, cls, priority, ranges, R, lower, float(voxel_size))
    return out


def _ground(ground: GroundRaster, T_global_from_level: np.ndarray, R: np.ndarray, grid: OccGrid) -> np.ndarray:
    """`(X, Y, Z) uint8`: the voxels whose level-frame box holds the ground plane (global z = 0) get
    the ground class at their centre; free elsewhere. For a level grid: the one layer that holds it."""
    lower, vs = np.asarray(grid.lower, np.float64), grid.voxel_size
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in grid.shape], indexing="ij"), -1) + 0.5
    # In voxel units, so that a level grid reproduces `ground_layer`'s floor((z - lower) / size) to the
    # bit: the plane on a voxel face belongs to the voxel above it.
    z_plane_u = (-T_global_from_level[2, 3] - R[2] @ lower) / vs
    q = idx @ R[2]
    ez_u = 0.5 * np.abs(R[2]).sum()
    on = (q - ez_u <= z_plane_u) & (z_plane_u < q + ez_u)
    sem = np.full(grid.shape, FREE_LABEL, np.uint8)
    centres_l = (lower + idx[on] * vs) @ R.T
    xy_g = centres_l[:, :2] @ T_global_from_level[:2, :2].T + T_global_from_level[:2, 3]
    sem[on] = ground.lookup(xy_g)
    return sem


def grid_semantics(ground: GroundRaster, prims: Primitives, T_global_from_grid: np.ndarray,
                   grid: OccGrid) -> np.ndarray:
    """Semantics `(X, Y, Z) uint8` (our 18 classes, 17 free) of the world on `grid`, laid out in the
    frame `T_global_from_grid (4, 4)` (any rigid frame: key ego, LIDAR_TOP)."""
    T_global_from_level, R = level_frame(T_global_from_grid)
    sem = _ground(ground, T_global_from_level, R, grid)
    params = primitives_to_frame(prims.params, T_global_from_level)
    return voxelize_tilted(sem, params, prims.cls, CLASS_PRIORITY, R, np.asarray(grid.lower), grid.voxel_size)
