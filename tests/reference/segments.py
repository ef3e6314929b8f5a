"""A segment-box test shared by the numpy twins (tests/reference): the slab test, written for clarity."""

from __future__ import annotations

import numpy as np

__all__ = ["segment_hits_boxes"]


def segment_hits_boxes(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether segment a->b `(3,)` meets each closed axis-aligned box `lo, hi (M, 3)`: `(M,) bool`.

    Per axis, the segment's parameter range inside the slab `[lo, hi]` is intersected with [0, 1]; an
    axis the segment runs parallel to keeps the range whole when `a` is within the slab, else empties it."""
    d = b - a
    t0, t1 = np.zeros(len(lo)), np.ones(len(lo))
    for k in range(3):
        if abs(d[k]) < 1e-15:
            inside = (a[k] >= lo[:, k]) & (a[k] <= hi[:, k])
            t1 = np.where(inside, t1, -1.0)
            continue
        ta, tb = (lo[:, k] - a[k]) / d[k], (hi[:, k] - a[k]) / d[k]
        t0 = np.maximum(t0, np.minimum(ta, tb))
        t1 = np.minimum(t1, np.maximum(ta, tb))
    return t0 <= t1
