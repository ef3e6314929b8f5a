"""Densification of generated labels: fill what LiDAR surfaces imply but no point landed in.

Generated labels hold the voxels that points fell in, so a solid is its observed skin. Three fills,
each limited by free-space evidence (`seen_free`: voxels a LiDAR ray passed through on its way to a
return, the last `FREE_MARGIN` metres before the return left out) so that a fill never claims space a
ray crossed. Only free voxels are filled; an observed voxel keeps its class.

- `fill_boxes`: an annotated object whose points are in the labels is a solid: the voxels whose
  centre lies in its box take its class.
- `fill_behind`: behind an observed voxel of a solid static class (manmade, vegetation, others), on
  the horizontal line from the sensor through it, the next `depth` voxels take its class, up to the
  first voxel a ray saw free. Buildings and tree crowns are solids the LiDAR sees the front of;
  `depth` defaults to the camera mask's `MAX_OCCLUDERS`, the depth to which Occ3D's camera mask
  scores an object's inside (docs/visibility.md): deeper fill would not be scored, only risked.
- `close_holes`: a free voxel with occupied voxels on both sides within `gap` voxels along at least
  two of the three axes lies in a surface (a hole in the road, a facade): it takes the most common
  class of those neighbours. An L-shaped corner (wall on ground) has them along one axis only, and
  the gap between two parallel surfaces along one axis, so neither is filled. Holes among ground
  classes are refused by a ray through the voxel below instead (`densify`: the ground is a height field).

Grids are `(X, Y, Z) uint8` semantics (17 = free) in the grid frame, `lower (3,) float64` its lower
corner, cubic voxels of `voxel_size` metres. Every numba kernel has a plain numpy twin (tests/reference/).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.sensors.raycast import segment_advance, segment_setup
from occdata.visibility import GROUND_CLASSES, MAX_OCCLUDERS

__all__ = ["DEPTH_M", "FREE_MARGIN", "GAP_M", "SOLID_STATIC", "close_holes", "densify", "fill_behind", "fill_boxes",
           "seen_free", "voxels_of"]

# Metres of each ray before its return that count as no evidence: a ray that grazes a surface crosses
# the voxels of that surface next to its return (the road in front of a ground return).
FREE_MARGIN = 0.4
# Distances in metres, as FREE_MARGIN is, so that a finer grid fills as far (`voxels_of`); on Occ3D's
# 0.4 m voxels they are the 2 and 7 voxels the fills were tuned with.
GAP_M = 0.8  # the widest hole `close_holes` bridges
DEPTH_M = MAX_OCCLUDERS * 0.4  # the camera mask's depth inside an object (MAX_OCCLUDERS Occ3D voxels)
# Occ3D classes that are solids whose inside no LiDAR sees: others, manmade, vegetation.
SOLID_STATIC = (0, 15, 16)


@njit(cache=True)
def seen_free(origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
              margin: float) -> np.ndarray:
    """`(X, Y, Z) uint8` 0/1: voxels crossed by rays `origins (N, 3) -> endpoints (N, 3)` (float64, grid
    frame) cut `margin` metres short of their endpoint, never the voxel holding the endpoint."""
    out = np.zeros((shape[0], shape[1], shape[2]), np.uint8)
    idx = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_next = np.empty(3)
    t_delta = np.empty(3)
    for n in range(origins.shape[0]):
        a, e = origins[n], endpoints[n]
        length = np.sqrt(((e - a) ** 2).sum())
        if length <= margin:
            continue
        b = a + (e - a) * (1.0 - margin / length)
        ok, t_end = segment_setup(a, b, lower, voxel_size, shape, idx, step, t_next, t_delta)
        if not ok:
            continue
        end = np.floor((e - lower) / voxel_size)
        while True:
            if idx[0] != end[0] or idx[1] != end[1] or idx[2] != end[2]:
                out[idx[0], idx[1], idx[2]] = 1
            if segment_advance(idx, step, t_next, t_delta, shape) > t_end:
                break
    return out


@njit(cache=True)
def fill_boxes(semantics: np.ndarray, free: np.ndarray, T_box_from_grid: np.ndarray, half_size: np.ndarray,
               lower: np.ndarray, voxel_size: float) -> np.ndarray:
    """`(X, Y, Z) int32`: for each voxel free in `semantics` and not seen free (`free`) whose centre lies
    in a box (closed; `T_box_from_grid (B, 4, 4)`, half extents `half_size (B, 3)`: length, width, height
    halves), the index of the first such box; -1 elsewhere."""
    X, Y, Z = semantics.shape
    out = np.full((X, Y, Z), -1, np.int32)
    for b in range(T_box_from_grid.shape[0]):
        T = T_box_from_grid[b]
        lo = np.empty(3)
        hi = np.empty(3)
        for a in range(3):  # the box's axis-aligned bounds in the grid frame, as voxel indices
            centre = -(T[0, a] * T[0, 3] + T[1, a] * T[1, 3] + T[2, a] * T[2, 3])
            reach = abs(T[0, a]) * half_size[b, 0] + abs(T[1, a]) * half_size[b, 1] + abs(T[2, a]) * half_size[b, 2]
            lo[a] = np.floor((centre - reach - lower[a]) / voxel_size - 0.5)
            hi[a] = np.ceil((centre + reach - lower[a]) / voxel_size - 0.5)
        for i in range(max(int(lo[0]), 0), min(int(hi[0]), X - 1) + 1):
            x = lower[0] + (i + 0.5) * voxel_size
            for j in range(max(int(lo[1]), 0), min(int(hi[1]), Y - 1) + 1):
                y = lower[1] + (j + 0.5) * voxel_size
                for k in range(max(int(lo[2]), 0), min(int(hi[2]), Z - 1) + 1):
                    if out[i, j, k] >= 0 or semantics[i, j, k] != FREE_LABEL or free[i, j, k] != 0:
                        continue
                    z = lower[2] + (k + 0.5) * voxel_size
                    if (abs(T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]) <= half_size[b, 0]
                            and abs(T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]) <= half_size[b, 1]
                            and abs(T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]) <= half_size[b, 2]):
                        out[i, j, k] = b
    return out


@njit(cache=True)
def fill_behind(semantics: np.ndarray, free: np.ndarray, solid: np.ndarray, origin_xy: np.ndarray, depth: int,
                lower: np.ndarray, voxel_size: float) -> np.ndarray:
    """A copy of `semantics` where, from each voxel whose class `c` has `solid[c]` (`solid (18,) bool`),
    the voxels on the horizontal line from `origin_xy (2,)` (the sensor, grid frame) through the voxel's
    centre, beyond it, are visited in order (2D DDA in the voxel's layer) up to `depth` of them: a free
    voxel not seen free takes class `c`; the walk stops at a voxel seen free, at one of another class in
    `semantics`, or at the grid's edge. Sources are the input's voxels only; where walks meet, the first
    source in (x, y, z) order wins."""
    X, Y, Z = semantics.shape
    out = semantics.copy()
    for i in range(X):
        for j in range(Y):
            for k in range(Z):
                c = semantics[i, j, k]
                if not solid[c]:
                    continue
                px = lower[0] + (i + 0.5) * voxel_size
                py = lower[1] + (j + 0.5) * voxel_size
                dx, dy = px - origin_xy[0], py - origin_xy[1]
                norm = np.sqrt(dx * dx + dy * dy)
                if norm == 0.0:
                    continue
                dx, dy = dx / norm, dy / norm
                si = 1 if dx > 0 else -1
                sj = 1 if dy > 0 else -1
                # ray from the centre: t to the next x / y face, and per voxel
                tx = 0.5 * voxel_size / abs(dx) if dx != 0 else np.inf
                ty = 0.5 * voxel_size / abs(dy) if dy != 0 else np.inf
                ddx = voxel_size / abs(dx) if dx != 0 else np.inf
                ddy = voxel_size / abs(dy) if dy != 0 else np.inf
                a, b = i, j
                for _ in range(depth):
                    if tx < ty:
                        a += si
                        tx += ddx
                    else:
                        b += sj
                        ty += ddy
                    if a < 0 or a >= X or b < 0 or b >= Y or free[a, b, k] != 0:
                        break
                    s = semantics[a, b, k]
                    if s == FREE_LABEL:
                        if out[a, b, k] == FREE_LABEL:
                            out[a, b, k] = c
                    elif s != c:
                        break
    return out


@njit(cache=True)
def close_holes(semantics: np.ndarray, free: np.ndarray, eligible: np.ndarray, gap: int) -> np.ndarray:
    """A copy of `semantics` where each free voxel not seen free (`free`) that has, along at least two of
    the axes x, y, z, a voxel of an `eligible (18,) bool` class within `gap` voxels on both sides (the
    nearest on each side) takes the most common class of those nearest neighbours (ties: the lower
    class). Sources are the input's voxels only."""
    X, Y, Z = semantics.shape
    shape = (X, Y, Z)
    out = semantics.copy()
    counts = np.zeros(NUM_CLASSES, np.int64)
    for i in range(X):
        for j in range(Y):
            for k in range(Z):
                if semantics[i, j, k] != FREE_LABEL or free[i, j, k] != 0:
                    continue
                counts[:] = 0
                axes = 0
                for ax in range(3):
                    found = 0
                    s1 = s2 = 0
                    for sign in (-1, 1):
                        for g in range(1, gap + 1):
                            a, b, c = i, j, k
                            if ax == 0:
                                a += sign * g
                            elif ax == 1:
                                b += sign * g
                            else:
                                c += sign * g
                            pos = (a, b, c)[ax]
                            if pos < 0 or pos >= shape[ax]:
                                break
                            s = semantics[a, b, c]
                            if s != FREE_LABEL:
                                if eligible[s]:
                                    found += 1
                                    s1, s2 = s2, s
                                break
                    if found == 2:
                        axes += 1
                        counts[s1] += 1
                        counts[s2] += 1
                if axes >= 2:
                    out[i, j, k] = np.argmax(counts)
    return out


def voxels_of(metres: float, voxel_size: float) -> int:
    """A distance in whole voxels (at least 1)."""
    return max(1, int(round(metres / voxel_size)))


def densify(semantics: np.ndarray, origin: np.ndarray, endpoints: np.ndarray, T_box_from_grid: np.ndarray,
            half_size: np.ndarray, box_classes: np.ndarray, lower: np.ndarray, voxel_size: float,
            static_rays: tuple[np.ndarray, np.ndarray] | None = None,
            solids: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """`semantics (X, Y, Z) uint8` with the fills of the module docstring: boxes first, then behind
    solid static surfaces, then holes. Evidence: the keyframe's rays from `origin (3,)` to `endpoints
    (N, 3)` (float64, grid frame; for several LiDARs `origin` is `(N, 3)`, one per ray), and for the
    static scene also `static_rays` (origins (M, 3), endpoints (M, 3): other keyframes' rays; the static
    scene does not move, objects may). Boxes: `T_box_from_grid
    (B, 4, 4)`, `half_size (B, 3)` (length, width, height halves), `box_classes (B,) uint8` (the objects
    whose points are in the labels). `solids` False (labels without lidarseg: every static voxel, the road
    too, has one class) skips the walk behind solid static surfaces, which would fill under the road.
    Returns the new semantics and `(X, Y, Z) int32` the box that filled each voxel (-1: none)."""
    lower = np.asarray(lower, np.float64)
    shape = np.asarray(semantics.shape, np.int64)
    ends = np.ascontiguousarray(endpoints, np.float64).reshape(-1, 3)
    origins = np.ascontiguousarray(np.broadcast_to(np.asarray(origin, np.float64), ends.shape))
    free = seen_free(origins, ends, lower, float(voxel_size), shape, FREE_MARGIN)
    free_static = free
    if static_rays is not None and len(static_rays[1]):
        more = [np.ascontiguousarray(a, np.float64).reshape(-1, 3) for a in static_rays]
        free_static = free | seen_free(more[0], more[1], lower, float(voxel_size), shape, FREE_MARGIN)
    owner = fill_boxes(semantics, free, np.ascontiguousarray(T_box_from_grid, np.float64).reshape(-1, 4, 4),
                       np.ascontiguousarray(half_size, np.float64).reshape(-1, 3), lower, float(voxel_size))
    cls = np.append(np.asarray(box_classes, np.uint8).reshape(-1), np.uint8(FREE_LABEL))  # owner -1: free
    out = np.where(owner >= 0, cls[owner], semantics).astype(np.uint8)
    # Several LiDARs (`origin (N, 3)`): the walks start from the first ray's origin, the reference LiDAR.
    origin_xy = np.asarray(origin, np.float64).reshape(-1, 3)[0, :2].copy()
    gap, depth = voxels_of(GAP_M, voxel_size), voxels_of(DEPTH_M, voxel_size)
    if solids:
        behind = fill_behind(semantics, free_static, np.isin(np.arange(NUM_CLASSES), SOLID_STATIC),
                             origin_xy, depth, lower, float(voxel_size))
        out = np.where(out == FREE_LABEL, behind, out)
    ground_cls = np.isin(np.arange(NUM_CLASSES), GROUND_CLASSES)
    holes = close_holes(semantics, free, (np.arange(NUM_CLASSES) != FREE_LABEL) & ~ground_cls, gap)
    out = np.where(out == FREE_LABEL, holes, out)
    # The ground is a height field: a ray grazing it crosses its voxels just above the surface and proves
    # nothing; only a ray through the voxel below shows the ground is not in this layer.
    below = np.zeros_like(free_static)
    below[:, :, 1:] = free_static[:, :, :-1]
    ground = close_holes(semantics, below, ground_cls, gap)
    return np.where(out == FREE_LABEL, ground, out), owner
