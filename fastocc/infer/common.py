"""Small pieces shared by `fastocc predict` and `fastocc eval`: the split's samples, the device."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from occdata.errors import OccDataError
from occdata.store.reader import StoreReader, open_store

__all__ = ["check_device", "split_indices"]


def split_indices(store: str | Path | StoreReader, split: str | None) -> np.ndarray:
    """Store indices of the built samples of `split` (None: all), ascending; an unknown split name is an
    `OccDataError` naming the store's splits (the loader yields exactly these samples)."""
    reader = store if isinstance(store, StoreReader) else open_store(store)
    return reader.split_indices(split)


def check_device(device: str) -> None:
    """One clear error for a device that is not there (instead of a CUDA traceback mid-run); "auto" (cuda
    when available, else cpu) is always there."""
    if device == "auto":
        return
    kind = torch.device(device).type
    if kind == "cuda" and not torch.cuda.is_available():
        raise OccDataError(f"device {device!r} asked for, but no CUDA device is available (use --device cpu)")
