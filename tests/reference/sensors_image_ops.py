"""Test oracles for `occdata.sensors.image_ops`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.sensors.image_ops import IMAGENET_MEAN, IMAGENET_STD

__all__ = ["normalise_chw_reference"]


def normalise_chw_reference(img: np.ndarray, mean: tuple[float, ...] = IMAGENET_MEAN,
                            std: tuple[float, ...] = IMAGENET_STD) -> np.ndarray:
    """Numpy twin of `normalise_chw` (computed directly, not through the table)."""
    x = img.astype(np.float64)
    out = (x - np.asarray(mean)) / np.asarray(std)
    return np.ascontiguousarray(out.transpose(2, 0, 1)).astype(np.float32)
