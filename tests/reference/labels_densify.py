"""Test oracles for `occdata.labels.densify`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.geometry import points_in_box
from reference.segments import segment_hits_boxes

__all__ = ["seen_free_reference", "fill_boxes_reference", "fill_behind_reference", "close_holes_reference"]


def seen_free_reference(origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float,
                        shape: np.ndarray, margin: float) -> np.ndarray:
    """Numpy twin of `seen_free`: every cut ray tested against every voxel's box."""
    shape = tuple(int(s) for s in shape)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    lo = lower + grid * voxel_size
    out = np.zeros(len(grid), bool)
    for a, e in zip(np.asarray(origins, np.float64), np.asarray(endpoints, np.float64), strict=True):
        length = np.linalg.norm(e - a)
        if length <= margin:
            continue
        hit = segment_hits_boxes(a, a + (e - a) * (1 - margin / length), lo, lo + voxel_size)
        end = np.floor((e - lower) / voxel_size).astype(np.int64)
        hit &= ~(grid == end).all(axis=1)
        out |= hit
    return out.reshape(shape).astype(np.uint8)


def fill_boxes_reference(semantics: np.ndarray, free: np.ndarray, T_box_from_grid: np.ndarray,
                         half_size: np.ndarray, lower: np.ndarray, voxel_size: float) -> np.ndarray:
    """Numpy twin of `fill_boxes`: every voxel centre tested against every box, the last box first."""
    out = np.full(semantics.shape, -1, np.int32)
    centres = lower + (np.argwhere(np.ones(semantics.shape, bool)) + 0.5) * voxel_size
    for b in range(len(T_box_from_grid) - 1, -1, -1):
        inside = points_in_box(centres, T_box_from_grid[b], half_size[b]).reshape(semantics.shape)
        out[inside & (semantics == FREE_LABEL) & (free == 0)] = b
    return out


def fill_behind_reference(semantics: np.ndarray, free: np.ndarray, solid: np.ndarray, origin_xy: np.ndarray,
                          depth: int, lower: np.ndarray, voxel_size: float) -> np.ndarray:
    """Numpy twin of `fill_behind`: the voxels of each walk found by sampling its line finely (every
    1/512 voxel) instead of a DDA."""
    X, Y, Z = semantics.shape
    out = semantics.copy()
    fine = np.arange(1, 512 * (depth + 2)) / 512 * voxel_size
    for i, j, k in np.argwhere(np.asarray(solid)[semantics]):
        c = semantics[i, j, k]
        p = lower[:2] + (np.array([i, j]) + 0.5) * voxel_size
        d = p - origin_xy
        if not np.any(d):
            continue
        cells = np.floor((p + fine[:, None] * d / np.linalg.norm(d) - lower[:2]) / voxel_size).astype(np.int64)
        keep = np.ones(len(cells), bool)
        keep[1:] = (cells[1:] != cells[:-1]).any(axis=1)
        cells = cells[keep]
        cells = cells[(cells != (i, j)).any(axis=1)][:depth]
        for a, b in cells:
            if not (0 <= a < X and 0 <= b < Y) or free[a, b, k]:
                break
            if semantics[a, b, k] == FREE_LABEL:
                if out[a, b, k] == FREE_LABEL:
                    out[a, b, k] = c
            elif semantics[a, b, k] != c:
                break
    return out


def close_holes_reference(semantics: np.ndarray, free: np.ndarray, eligible: np.ndarray, gap: int) -> np.ndarray:
    """Numpy twin of `close_holes`: per axis and side, the nearest occupied voxel within `gap` found by
    shifting whole grids."""
    occ = semantics != FREE_LABEL
    counts = np.zeros((NUM_CLASSES, *semantics.shape), np.int64)
    axes = np.zeros(semantics.shape, np.int64)
    for ax in range(3):
        both = np.ones(semantics.shape, bool)
        side_cls = []
        for sign in (-1, 1):
            cls = np.full(semantics.shape, FREE_LABEL, np.int64)
            for g in range(gap, 0, -1):  # nearer overwrites farther
                shifted = np.full(semantics.shape, FREE_LABEL, np.int64)
                src = [slice(None)] * 3
                dst = [slice(None)] * 3
                n = semantics.shape[ax]
                if sign > 0:
                    src[ax], dst[ax] = slice(g, n), slice(0, n - g)
                else:
                    src[ax], dst[ax] = slice(0, n - g), slice(g, n)
                shifted[tuple(dst)] = semantics[tuple(src)]
                cls = np.where(shifted != FREE_LABEL, shifted, cls)
            ok = (cls != FREE_LABEL) & np.asarray(eligible)[np.minimum(cls, FREE_LABEL)]
            both &= ok
            side_cls.append(cls)
        axes += both
        for cls in side_cls:
            for c in range(NUM_CLASSES):
                counts[c] += both & (cls == c)
    take = ~occ & (free == 0) & (axes >= 2)
    out = semantics.copy()
    out[take] = np.argmax(counts, axis=0)[take]
    return out
