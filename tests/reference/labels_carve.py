"""Test oracles for `occdata.labels.carve`: plain numpy twins of its kernels, which the tests compare the
kernels against (nothing in occdata uses them). Rays are tested against every voxel's box (a slab test),
not stepped with a DDA."""

from __future__ import annotations

import numpy as np

from reference.segments import segment_hits_boxes

__all__ = ["carve_reference", "dynamic_reference"]


def _voxel(points: np.ndarray, lower: np.ndarray, voxel_size: float,
           shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    idx = np.floor((np.asarray(points, np.float64).reshape(-1, 3) - lower) / voxel_size).astype(np.int64)
    return idx, ((idx >= 0) & (idx < shape)).all(axis=1)


def carve_reference(slots: list[list[tuple[np.ndarray, np.ndarray]]], lower: np.ndarray, voxel_size: float,
                    shape: np.ndarray, margin: float, graze_max: float, graze_height: float,
                    near: int) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin of `CarveGrid.add_slot` (heights not aligned) over time slots `slots[s]` = [(origin (3,),
    points (N, 3)), ...]: `(hits, crossed)` `(X, Y, Z) int64` (not saturated): per voxel, the slots with a
    return in it, and the slots one of whose rays, cut `clamp(graze_height / |sin elevation|, margin,
    graze_max)` short of its return, meets the voxel's closed box, the return's own voxel and every voxel
    within `near` voxels (per axis) of the slot's hit voxels left out."""
    shape = np.asarray(shape, np.int64)
    cells = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    lo = lower + cells * voxel_size
    hits = np.zeros(len(cells), np.int64)
    crossed = np.zeros(len(cells), np.int64)
    flat = np.ravel_multi_index(cells.T, tuple(shape))
    for frames in slots:
        hit = np.zeros(len(cells), bool)
        every = []  # every return's voxel, inside the grid or not: one just outside still blocks its neighbours
        for _, pts in frames:
            idx, ok = _voxel(pts, lower, voxel_size, shape)
            hit[np.ravel_multi_index(idx[ok].T, tuple(shape))] = True
            every.append(idx)
        cross = np.zeros(len(cells), bool)
        for origin, pts in frames:
            for e in np.asarray(pts, np.float64).reshape(-1, 3):
                a = np.asarray(origin, np.float64)
                length = np.linalg.norm(e - a)
                if length == 0:
                    continue
                sin = abs(e[2] - a[2]) / length
                graze = graze_max if sin * graze_max <= graze_height else graze_height / sin
                graze = max(graze, margin)
                if length <= graze:
                    continue
                meets = segment_hits_boxes(a, a + (e - a) * (1 - graze / length), lo, lo + voxel_size)
                end = np.floor((e - lower) / voxel_size).astype(np.int64)
                meets &= ~(cells == end).all(axis=1)
                cross |= meets
        hit_cells = np.concatenate(every) if every else np.zeros((0, 3), np.int64)
        blocked = (np.abs(cells[:, None, :] - hit_cells[None, :, :]) <= near).all(axis=2).any(axis=1)
        hits += hit[flat]
        crossed += (cross & ~blocked)[flat]
    return hits.reshape(tuple(shape)), crossed.reshape(tuple(shape))


def dynamic_reference(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
                      hits: np.ndarray, crossed: np.ndarray, min_frames: int, ratio: float) -> np.ndarray:
    """Numpy twin of `dynamic_points`."""
    idx, ok = _voxel(points, lower, voxel_size, np.asarray(shape))
    out = np.zeros(len(idx), bool)
    c, h = crossed[tuple(idx[ok].T)].astype(np.float64), hits[tuple(idx[ok].T)]
    out[ok] = (c >= min_frames) & (c >= ratio * h)
    return out
