"""`occdata bev-gt`: (re)compute the BEV multi-hot GT of every labelled sample from its semantics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr

from occdata.errors import OccDataError
from occdata.runtime.lock import store_lock
from occdata.store.bev import bev_bits
from occdata.store.integrity import StoreIntegrity
from occdata.store.reader import store_location
from occdata.store.update import update_samples

__all__ = ["compute_bev_gt"]


def compute_bev_gt(store: str | Path, block: int = 32, progress: bool = True) -> int:
    """Returns the number of samples written. Runs as part of `occdata build` already."""
    try:
        group = zarr.open_group(store_location(store), mode="r+")
    except Exception as exc:  # noqa: BLE001
        raise OccDataError(f"not a readable occdata store: {store} ({type(exc).__name__})") from None

    def fn(a: dict[str, np.ndarray], _i: int) -> dict[str, np.ndarray]:
        return {"labels/bev": bev_bits(a["labels/semantics"])}

    with store_lock(store_location(store), "bev-gt"):  # one writer at a time (a build, visibility, another bev-gt)
        present = StoreIntegrity(group).read_state() != 0  # checked commit flags first
        present &= group["labels/present"][:]
        return update_samples(group, ("labels/semantics",), fn, present, block, "bev-gt", progress)
