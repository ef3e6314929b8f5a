"""Small per-sample arrays handed to DataLoader workers without a re-read: shared memory.

The loader's parent process reads the store's small arrays once (`StoreSamples`). A forked worker
inherits them. A worker started by forkserver or spawn gets the dataset pickled; each array then
travels as a torch uint8 tensor in shared memory (torch's pickler passes its file descriptor), so W
workers map one copy instead of each reading the store again. The copy into shared memory happens
once per array, at the first pickle; later ones (each epoch's new workers) only pass descriptors.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["SharedArray", "from_shared", "to_shared"]

SharedArray = tuple[torch.Tensor, str, tuple[int, ...]]  # bytes in shared memory, numpy dtype, shape


def to_shared(arr: np.ndarray) -> SharedArray:
    """`arr` (any dtype and shape) copied once into a shared-memory uint8 tensor."""
    arr = np.ascontiguousarray(arr)
    flat = torch.empty(arr.nbytes, dtype=torch.uint8).share_memory_()
    flat.numpy()[:] = arr.reshape(-1).view(np.uint8)
    return flat, arr.dtype.str, arr.shape


def from_shared(shared: SharedArray) -> np.ndarray:
    """The read-only numpy view of a `to_shared` array (no copy; the view keeps the tensor alive)."""
    flat, dtype, shape = shared
    out = flat.numpy().view(np.dtype(dtype)).reshape(shape)
    out.flags.writeable = False
    return out
