"""Test oracles for `occdata.eval.miou`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.constants import NUM_CLASSES

__all__ = ["confusion_matrix_reference"]


def confusion_matrix_reference(gt: np.ndarray, pred: np.ndarray, mask: np.ndarray | None = None,
                               num_classes: int = NUM_CLASSES) -> np.ndarray:
    """Numpy twin of `confusion_matrix` (no label checks): `(K, K) int64`, rows = truth."""
    g = np.asarray(gt).ravel().astype(np.int64)
    p = np.asarray(pred).ravel().astype(np.int64)
    keep = (p < num_classes) & (g < num_classes)
    if mask is not None:
        keep &= np.asarray(mask).ravel() != 0
    flat = g[keep] * num_classes + p[keep]
    return np.bincount(flat, minlength=num_classes * num_classes).reshape(num_classes, num_classes)
