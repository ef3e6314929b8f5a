"""Recompute some per-sample arrays of a committed store in place, keeping checksums valid.

Used by `occdata bev-gt` and `occdata visibility`. Work goes block by block; within a block the
arrays are written first and the checksum row last, so `occdata verify` flags an interrupted update
and a rerun repairs it.
"""

from __future__ import annotations

import warnings
import zlib
from collections.abc import Callable

import numpy as np
import zarr
from tqdm import tqdm
from zarr import consolidate_metadata

from occdata.store.integrity import StoreIntegrity
from occdata.store.layout import STATE_DONE, checksummed_names, has_flow
from occdata.store.pack import drop_pack, write_pack

__all__ = ["update_samples"]

# fn(block of input arrays, each (n, ...)) -> block of output arrays, or None to leave a sample as is.
UpdateFn = Callable[[dict[str, np.ndarray], int], dict[str, np.ndarray] | None]


def update_samples(
    group: zarr.Group,
    inputs: tuple[str, ...],
    fn: UpdateFn,
    select: np.ndarray,
    block: int,
    desc: str,
    progress: bool = True,
) -> int:
    """Call `fn(sample_inputs, index)` for every selected committed sample and write its outputs.

    `select` is an `(N,) bool` mask. Returns the number of samples updated.
    """
    names = checksummed_names(has_flow(group.attrs))
    drop_pack(group)  # small arrays may change: readers use the chunks until the copies are rewritten
    integrity = StoreIntegrity(group)
    state = integrity.read_state()
    todo = np.flatnonzero(select & (state == STATE_DONE))
    n_done = 0
    with tqdm(total=len(todo), desc=desc, unit="sample", disable=not progress, dynamic_ncols=True) as bar:
        for b0 in range(0, group["status/state"].shape[0], block):
            idx = todo[(todo >= b0) & (todo < b0 + block)]
            if not len(idx):
                continue
            i0, i1 = int(idx[0]), int(idx[-1]) + 1
            data = {name: group[name][i0:i1] for name in inputs}
            for name in inputs:  # never recompute from (and re-checksum) a chunk that went missing
                if name in names:
                    integrity.check_rows(name, idx, [data[name][i - i0] for i in idx])
            outs: dict[str, np.ndarray] = {}
            touched: list[int] = []
            for i in idx:
                result = fn({k: v[i - i0] for k, v in data.items()}, int(i))
                bar.update(1)
                if result is None:
                    continue
                for k, v in result.items():
                    if k not in outs:
                        outs[k] = group[k][i0:i1]
                    outs[k][i - i0] = v
                touched.append(int(i))
            if not touched:
                continue
            for k, v in outs.items():
                group[k][i0:i1] = v
            sums = group["status/checksum"][i0:i1]
            for i in touched:
                for k, v in outs.items():
                    sums[i - i0, names.index(k)] = zlib.crc32(np.ascontiguousarray(v[i - i0]).tobytes())
            group["status/checksum"][i0:i1] = sums
            n_done += len(touched)
    write_pack(group)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zarr: consolidated metadata is not (yet) in the v3 spec
        consolidate_metadata(group.store)
    return n_done
