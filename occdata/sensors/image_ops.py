"""Image normalisation kernel for the loader (no torch): HWC uint8 -> CHW float32 in one pass.

A per-channel lookup table (256 entries) replaces subtract + divide + transpose, which numpy would
do in three passes over a float copy. `normalise_chw_reference` (tests/reference/) is the numpy twin.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "normalise_chw", "normalise_lut"]

IMAGENET_MEAN = (123.675, 116.28, 103.53)  # RGB, docs/design.md#augmentation
IMAGENET_STD = (58.395, 57.12, 57.375)


def normalise_lut(mean: tuple[float, ...] = IMAGENET_MEAN, std: tuple[float, ...] = IMAGENET_STD) -> np.ndarray:
    """`(3, 256) float32`: lut[c, x] = (x - mean[c]) / std[c]."""
    x = np.arange(256, dtype=np.float64)[None, :]
    m = np.asarray(mean, dtype=np.float64)[:, None]
    s = np.asarray(std, dtype=np.float64)[:, None]
    return ((x - m) / s).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def normalise_chw(img: np.ndarray, lut: np.ndarray, out: np.ndarray) -> None:
    """img `(H, W, 3) uint8` RGB -> out `(3, H, W) float32` (written in place) via `lut (3, 256)`."""
    h, w = img.shape[0], img.shape[1]
    for c in range(3):
        for y in range(h):
            for x in range(w):
                out[c, y, x] = lut[c, img[y, x, c]]
