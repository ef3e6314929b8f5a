"""Test oracles for `occdata.labels.carve`: plain numpy twins of its kernels, which the tests compare the
kernels against (nothing in occdata uses them). Rays are tested against every voxel's box (a slab test),
not stepped with a DDA."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from reference.segments import segment_hits_boxes

__all__ = ["carve_reference", "dynamic_reference", "gone_reference"]


def _voxel(points: np.ndarray, lower: np.ndarray, voxel_size: float,
           shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    idx = np.floor((np.asarray(points, np.float64).reshape(-1, 3) - lower) / voxel_size).astype(np.int64)
    return idx, ((idx >= 0) & (idx < shape)).all(axis=1)


def carve_reference(slots: list[list[tuple[np.ndarray, np.ndarray]]], lower: np.ndarray, voxel_size: float,
                    shape: np.ndarray, margin: float, graze_max: float, graze_height: float,
                    near: int, up_of: Callable[[np.ndarray], np.ndarray] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`(hits, crossed)` summed over `slot_evidence`."""
    per_slot = slot_evidence(slots, lower, voxel_size, shape, margin, graze_max, graze_height, near, up_of)
    hits = sum((h.astype(np.int64) for h, _ in per_slot), np.zeros(tuple(shape), np.int64))
    crossed = sum((c.astype(np.int64) for _, c in per_slot), np.zeros(tuple(shape), np.int64))
    return hits, crossed


def gone_reference(per_slot: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """`(before, after)` `(X, Y, Z) int64` from `slot_evidence` in time order: per voxel, the slots that
    crossed it before its first hit slot (all of them where none hit: unused then), and those after its
    last hit slot (0 where none hit)."""
    hit = np.stack([h for h, _ in per_slot])
    cross = np.stack([c for _, c in per_slot]).astype(np.int64)
    n = len(per_slot)
    order = np.arange(n).reshape(n, *([1] * (hit.ndim - 1)))
    first = np.where(hit.any(axis=0), np.argmax(hit, axis=0), n)
    last = np.where(hit.any(axis=0), n - 1 - np.argmax(hit[::-1], axis=0), n)
    return (cross * (order < first)).sum(axis=0), (cross * (order > last)).sum(axis=0)


def slot_evidence(slots: list[list[tuple[np.ndarray, np.ndarray]]], lower: np.ndarray, voxel_size: float,
                  shape: np.ndarray, margin: float, graze_max: float, graze_height: float,
                  near: int, up_of: Callable[[np.ndarray], np.ndarray] | None = None
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Numpy twin of `CarveGrid.add_slot` (heights not aligned) over time slots `slots[s]` = [(origin (3,),
    points (N, 3)), ...]: per slot `(hit, crossed)` `(X, Y, Z) bool`: the voxels with a
    return of the slot, and those one of whose rays, cut `clamp(graze_height / |sin elevation|, margin,
    graze_max)` short of its return, meets the voxel's closed box, the return's own voxel and every voxel
    within `near` voxels in x and y, and from `near` below to `up_of(points) (N,)` above in z (None:
    `near`), of the slot's hit voxels left out."""
    shape = np.asarray(shape, np.int64)
    cells = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    lo = lower + cells * voxel_size
    out = []
    flat = np.ravel_multi_index(cells.T, tuple(shape))
    for frames in slots:
        hit = np.zeros(len(cells), bool)
        every, ups = [], []  # every return's voxel, inside the grid or not: one just outside still blocks
        for _, pts in frames:
            idx, ok = _voxel(pts, lower, voxel_size, shape)
            hit[np.ravel_multi_index(idx[ok].T, tuple(shape))] = True
            every.append(idx)
            ups.append(np.full(len(idx), near) if up_of is None else up_of(np.asarray(pts, np.float64).reshape(-1, 3)))
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
        up = np.concatenate(ups) if ups else np.zeros(0, np.int64)
        d = cells[:, None, :] - hit_cells[None, :, :]
        blocked = ((np.abs(d[..., :2]) <= near).all(axis=2) & (d[..., 2] >= -near) & (d[..., 2] <= up)).any(axis=1)
        out.append((hit[flat].reshape(tuple(shape)), (cross & ~blocked)[flat].reshape(tuple(shape))))
    return out


def dynamic_reference(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
                      hits: np.ndarray, crossed: np.ndarray, min_frames: int, ratio: float,
                      before: np.ndarray | None = None, after: np.ndarray | None = None,
                      min_gone: int = 0) -> np.ndarray:
    """Numpy twin of `dynamic_points` (`before`, `after`: `gone_reference`; None with `min_gone` 0)."""
    idx, ok = _voxel(points, lower, voxel_size, np.asarray(shape))
    out = np.zeros(len(idx), bool)
    c, h = crossed[tuple(idx[ok].T)].astype(np.float64), hits[tuple(idx[ok].T)]
    out[ok] = (c >= min_frames) & (c >= ratio * h)
    if min_gone > 0:
        b, a = before[tuple(idx[ok].T)], after[tuple(idx[ok].T)]
        out[ok] |= (h > 0) & ((b >= min_gone) | (a >= min_gone))
    return out
