"""Test oracles for `occdata.store.bev`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

__all__ = ["bev_bits_reference"]


def bev_bits_reference(semantics: np.ndarray) -> np.ndarray:
    """Numpy twin of `bev_bits`."""
    sem = semantics.astype(np.uint32)
    onehot = np.where(sem < 32, np.left_shift(np.uint32(1), np.minimum(sem, 31)), np.uint32(0))
    return np.bitwise_or.reduce(onehot.astype(np.uint32), axis=2)
