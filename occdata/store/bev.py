"""BEV multi-hot ground truth from voxel labels (docs/design.md#the-store-layout).

Stored as one uint32 bit field per BEV cell: bit c is set when any voxel of the column has label c.
`free` (17) is a bit too, so consumers can choose whether it is a channel of the target.
"""

from __future__ import annotations

import numba
import numpy as np

from occdata.constants import NUM_CLASSES

__all__ = ["bev_bits", "unpack_bev"]


@numba.njit(cache=True, nogil=True)
def bev_bits(semantics: np.ndarray) -> np.ndarray:
    """`(X, Y, Z) uint8` labels -> `(X, Y) uint32` bit field (bit c: class c in the column).

    Labels >= 32 cannot be represented and are ignored.
    """
    nx, ny, nz = semantics.shape
    out = np.zeros((nx, ny), dtype=np.uint32)
    for i in range(nx):
        for j in range(ny):
            bits = np.uint32(0)
            for k in range(nz):
                c = semantics[i, j, k]
                if c < 32:
                    bits |= np.uint32(1) << np.uint32(c)
            out[i, j] = bits
    return out


def unpack_bev(bits: np.ndarray, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """`(..., X, Y) uint32` bit field -> `(..., num_classes, X, Y) uint8` multi-hot."""
    shifts = np.arange(num_classes, dtype=np.uint32).reshape((num_classes, 1, 1))
    return ((bits[..., None, :, :] >> shifts) & 1).astype(np.uint8)
