"""Test oracles for `occdata.eval.rayiou`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.constants import FREE_LABEL, GRID, OccGrid
from occdata.eval.rayiou import _MAX_STEPS, _check_grid, _ray_setup, _rays, _to_metres

__all__ = ["first_hits_reference", "march_reference"]


def first_hits_reference(labels: np.ndarray, origins_keyego: np.ndarray, directions: np.ndarray | None = None,
                         grid: OccGrid = GRID, free_label: int = FREE_LABEL) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin of `first_hits`: the same traversal, all rays stepped together."""
    dist, cls, _ = march_reference(labels, origins_keyego, directions, grid, free_label)
    return dist, cls


def march_reference(labels: np.ndarray, origins_keyego: np.ndarray, directions: np.ndarray | None = None,
                    grid: OccGrid = GRID, free_label: int = FREE_LABEL) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`first_hits_reference` plus each ray's first-hit voxel as a flat index `(n, R) int64` into
    `labels.ravel()` (-1: no hit): the numpy twin of the casting kernels' third output."""
    lab = _check_grid(labels, grid, "labels")
    dirs = _rays() if directions is None else np.asarray(directions, np.float32).reshape(-1, 3)
    o_v, e_v = _ray_setup(origins_keyego, dirs, grid)
    n, R = e_v.shape[:2]
    o = np.repeat(o_v.astype(np.float64), R, axis=0)
    r = e_v.reshape(-1, 3).astype(np.float64) - o
    d = r / np.sqrt(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1] + r[:, 2] * r[:, 2])[:, None]
    v = np.floor(o).astype(np.int64)
    s = np.where(d >= 0, 1, -1)
    big = np.finfo(np.float64).max
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d != 0, (v + (s > 0) - o) / d, big)
        dt = np.where(d != 0, s / d, big)
    shape = np.array(lab.shape)
    dist = np.full(n * R, np.nan)
    cls = np.full(n * R, free_label, np.uint8)
    index = np.full(n * R, -1, np.int64)
    active = np.ones(n * R, bool)
    was_inside = np.zeros(n * R, bool)
    rows = np.arange(n * R)
    for _ in range(_MAX_STEPS + 1):
        if not active.any():
            break
        inside = np.all((v >= 0) & (v < shape), axis=1)
        was_inside |= inside
        active &= inside | ~was_inside
        # axis to step: x if tx < ty and tx < tz; y if not (tx < ty) and ty < tz; else z
        ax = np.where(t[:, 0] < t[:, 1], np.where(t[:, 0] < t[:, 2], 0, 2), np.where(t[:, 1] < t[:, 2], 1, 2))
        t_exit = t[rows, ax]
        vi = np.clip(v, 0, shape - 1)
        lab_here = lab[vi[:, 0], vi[:, 1], vi[:, 2]]
        hit = active & inside & (lab_here != free_label)
        dist[hit] = t_exit[hit]
        cls[hit] = lab_here[hit]
        index[hit] = np.ravel_multi_index(tuple(vi[hit].T), lab.shape)
        active &= ~hit
        v[rows, ax] += s[rows, ax]
        t[rows, ax] += dt[rows, ax]
    return _to_metres(dist.reshape(n, R), grid), cls.reshape(n, R), index.reshape(n, R)
