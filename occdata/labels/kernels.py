"""Numba kernels of label generation, each with a plain numpy twin (tests/reference/: they agree).

- `points_in_boxes`: which 3D box (if any) holds each point.
- `vote_voxels`: transform points into a voxel grid's frame, one (voxel, class) vote key per point
  (`majority` then takes the most voted class per voxel).
- `nearest_labels`: the class of each query point's nearest labelled reference point within a radius.
- `vote_sources` (numpy only): which vote list (static scene or one box) gave each voxel its class,
  for occupancy flow.

Boxes are given by `T_box_from_world (B, 4, 4) float64` and half extents `half_size (B, 3) float64`
(box frame: x along the length, y along the width, z up, origin at the centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

__all__ = [
    "NO_LABEL",
    "NearestIndex",
    "nearest_labels",
    "points_in_boxes",
    "majority",
    "vote_sources",
    "vote_voxels",
]

NO_LABEL = 255  # a point without a class (no reference within the radius)


@njit(cache=True, parallel=True)
def points_in_boxes(points: np.ndarray, T_box_from_world: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """`(N,) int32`: index of the first box (in box order) whose closed volume holds each point of
    `points (N, 3) float64`, or -1."""
    n, nb = points.shape[0], T_box_from_world.shape[0]
    out = np.full(n, -1, np.int32)
    for i in prange(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for b in range(nb):
            T = T_box_from_world[b]
            bx = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            if abs(bx) > half_size[b, 0]:
                continue
            by = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            if abs(by) > half_size[b, 1]:
                continue
            bz = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            if abs(bz) > half_size[b, 2]:
                continue
            out[i] = b
            break
    return out


@njit(cache=True)
def vote_voxels(
    points: np.ndarray, classes: np.ndarray, T_grid_from_world: np.ndarray, lower: np.ndarray, voxel_size: float,
    shape: np.ndarray, n_classes: int,
) -> np.ndarray:
    """One vote per point as a key `flat voxel index * n_classes + class`, `(M,) int64` (M <= N).

    points `(N, 3) float64` in the world frame, moved into the grid frame by `T_grid_from_world
    (4, 4)`; classes `(N,) uint8` (values >= n_classes are skipped); points outside the grid too. A
    voxel is [lower + i v, lower + (i + 1) v) per axis; the flat index is (ix * Y + iy) * Z + iz.
    Keys, not a dense (voxels, classes) count table: memory follows the points, not the grid (a
    512 x 512 x 40 grid's table took 0.7 GB)."""
    X, Y, Z = shape[0], shape[1], shape[2]
    T = T_grid_from_world
    out = np.empty(points.shape[0], np.int64)
    m = 0
    for i in range(points.shape[0]):
        c = classes[i]
        if c >= n_classes:
            continue
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        ix = int(np.floor((T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3] - lower[0]) / voxel_size))
        iy = int(np.floor((T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3] - lower[1]) / voxel_size))
        iz = int(np.floor((T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3] - lower[2]) / voxel_size))
        if 0 <= ix < X and 0 <= iy < Y and 0 <= iz < Z:
            out[m] = ((ix * Y + iy) * Z + iz) * n_classes + c
            m += 1
    return out[:m]


def majority(votes: list[np.ndarray], shape: tuple[int, int, int], n_classes: int, empty: int) -> np.ndarray:
    """`(X, Y, Z) uint8`: per voxel the class with the most votes among the keys of `votes` (each
    `vote_voxels`' output), ties to the lowest class index; `empty` where a voxel has no vote."""
    voxel, cls = _most_voted(np.concatenate([np.zeros(0, np.int64), *votes]), n_classes)
    out = np.full(int(np.prod(shape)), empty, np.uint8)
    out[voxel] = cls
    return out.reshape(shape)


def _most_voted(keys: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Keys `group * n + item` `(M,) int64`, one per vote -> per group (ascending) the item with the most
    votes, ties to the lowest item: `group (G,)`, `item (G,)` int64."""
    keys, counts = np.unique(keys, return_counts=True)
    group, item = np.divmod(keys, n)
    order = np.lexsort((item, -counts, group))
    group, item = group[order], item[order]
    first = np.ones(len(group), bool)
    first[1:] = group[1:] != group[:-1]
    return group[first], item[first]


def vote_sources(votes: list[np.ndarray], semantics: np.ndarray, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """Which vote list gave each voxel its class. `votes[s]` are source s's `vote_voxels` keys (source 0
    the static scene, 1.. one placed box each); `semantics (X, Y, Z) uint8` is `majority`'s output.

    Returns `voxel (V,) int64` flat indices of the voxels some source s >= 1 votes in, and `source (V,)
    int64`: the source with the most votes there for the voxel's class, ties to the lowest s (so the
    static scene wins a tie). Source 0's votes elsewhere are never sorted: a scene's static points
    outnumber its boxes' by far."""
    if len(votes) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cand = np.unique(np.concatenate([np.zeros(0, np.int64), *votes[1:]]) // n_classes)
    winner_flat = semantics.reshape(-1)
    vox_l, src_l = [], []
    for s, keys in enumerate(votes):
        vox, cls = np.divmod(keys, n_classes)
        if s == 0 and len(cand):
            pos = np.minimum(np.searchsorted(cand, vox), len(cand) - 1)
            vox, cls = vox[cand[pos] == vox], cls[cand[pos] == vox]
        keep = cls == winner_flat[vox]
        vox_l.append(vox[keep])
        src_l.append(np.full(int(keep.sum()), s, np.int64))
    return _most_voted(np.concatenate(vox_l) * len(votes) + np.concatenate(src_l), len(votes))


@njit(cache=True)
def _cell_key(cx: int, cy: int, cz: int) -> int:
    # 21 bits per axis (cells of >= 1 cm cover +-10 km): a unique, order-preserving int64 key.
    return ((cx + (1 << 20)) << 42) | ((cy + (1 << 20)) << 21) | (cz + (1 << 20))


@njit(cache=True)
def _cell_keys(points: np.ndarray, cell: float) -> np.ndarray:
    keys = np.empty(points.shape[0], np.int64)
    for i in range(points.shape[0]):
        keys[i] = _cell_key(int(np.floor(points[i, 0] / cell)), int(np.floor(points[i, 1] / cell)),
                            int(np.floor(points[i, 2] / cell)))
    return keys


@njit(cache=True, parallel=True)
def _nearest_sorted(
    query: np.ndarray, ref: np.ndarray, ref_cls: np.ndarray, keys: np.ndarray, orig: np.ndarray, radius: float
) -> np.ndarray:
    out = np.full(query.shape[0], NO_LABEL, np.uint8)
    dist2 = np.full(query.shape[0], np.inf)
    r2 = radius * radius
    for q in prange(query.shape[0]):
        x, y, z = query[q, 0], query[q, 1], query[q, 2]
        fx, fy, fz = np.floor(x / radius), np.floor(y / radius), np.floor(z / radius)
        cx, cy, cz = int(fx), int(fy), int(fz)
        # Distances from the point to its cell's lower and upper faces, per axis.
        lo = np.array([x - fx * radius, y - fy * radius, z - fz * radius])
        hi = radius - lo
        best, best_j = r2, -1
        for n in range(27):  # own cell first (n = 13 is (0, 0, 0)), then the neighbours
            m = (n + 13) % 27
            dx, dy, dz = m // 9 - 1, (m // 3) % 3 - 1, m % 3 - 1
            # Skip a neighbour cell that cannot hold anything nearer than the best so far.
            gap = 0.0
            for axis, d in ((0, dx), (1, dy), (2, dz)):
                if d < 0:
                    gap += lo[axis] ** 2
                elif d > 0:
                    gap += hi[axis] ** 2
            if gap > best:
                continue
            k = _cell_key(cx + dx, cy + dy, cz + dz)
            j = np.searchsorted(keys, k)
            while j < keys.shape[0] and keys[j] == k:
                d2 = (ref[j, 0] - x) ** 2 + (ref[j, 1] - y) ** 2 + (ref[j, 2] - z) ** 2
                # Nearest wins; an equal distance goes to the reference first in input order.
                if d2 <= r2 and (best_j < 0 or d2 < best or (d2 == best and orig[j] < orig[best_j])):
                    best, best_j = d2, j
                j += 1
        if best_j >= 0:
            out[q] = ref_cls[best_j]
            dist2[q] = best
    return out, dist2


@dataclass(frozen=True, eq=False)
class NearestIndex:
    """Labelled reference points bucketed in cells of `radius` metres, sorted by cell, for repeated
    `query` calls (built once per scene). `ref (R, 3) float64`, `cls (R,) uint8` in sorted order;
    `keys (R,) int64` their cells; `orig (R,) int64` their input positions (for tie-breaking)."""

    ref: np.ndarray
    cls: np.ndarray
    keys: np.ndarray
    orig: np.ndarray
    radius: float

    @staticmethod
    def build(ref: np.ndarray, ref_cls: np.ndarray, radius: float) -> NearestIndex:
        if radius <= 0:
            raise ValueError("radius must be > 0")
        ref = np.ascontiguousarray(ref, np.float64).reshape(-1, 3)
        keys = _cell_keys(ref, float(radius))
        order = np.argsort(keys, kind="stable")
        return NearestIndex(ref[order], np.ascontiguousarray(np.asarray(ref_cls, np.uint8)[order]), keys[order],
                            order.astype(np.int64), float(radius))

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`(Q,) uint8` class of the nearest reference within `radius` (inclusive) of each point of
        `points (Q, 3)`, or NO_LABEL; and `(Q,) float64` its squared distance (inf: none). Ties go
        to the reference first in input order."""
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        if len(self.ref) == 0:
            return np.full(len(points), NO_LABEL, np.uint8), np.full(len(points), np.inf)
        return _nearest_sorted(points, self.ref, self.cls, self.keys, self.orig, self.radius)


def nearest_labels(query: np.ndarray, ref: np.ndarray, ref_cls: np.ndarray, radius: float) -> np.ndarray:
    """One-off `NearestIndex.build(ref, ref_cls, radius).query(query)`, classes only."""
    return NearestIndex.build(ref, ref_cls, radius).query(query)[0]
