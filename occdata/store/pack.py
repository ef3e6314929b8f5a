"""The small per-sample arrays packed for readers: one chunk per array and 16,384 samples, read in
one request each.

The build writes each small array (poses, calibration, offsets, state, checksums...) in chunks of one
block, so that every task owns its chunks: 1,063 chunks per array at 34,000 samples. A reader wants
them whole. At the build's final commit the client copies each small array into `pack/<name>`, ONE
chunk, and stamps the copies and the root attribute `pack` with the same generation (a digest of
their content). A reader
uses the copy only when both generations agree (they come with the consolidated metadata, so checking
costs no request) and the copy's crc32 matches its attribute; otherwise it reads the block chunks.

A writer that may change a small array drops the root attribute first (`drop_pack`): a resumed build
(`occdata.store.create`) and `update_samples` (bev-gt, visibility). A run killed before its final commit
leaves no valid pack, and readers fall back to the chunks. Cost: the small arrays stored twice (~3.5 KB
per sample before compression) and, at the commit, one read of every small chunk.
"""

from __future__ import annotations

import hashlib
import zlib
from typing import Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from occdata.store.layout import camera_count, grid_shape, has_flow, per_sample

__all__ = ["PACK_ATTR", "PACK_GROUP", "drop_pack", "pack_names", "packed_crc", "write_pack"]

PACK_ATTR = "pack"  # root attribute: {"generation": hex}
PACK_GROUP = "pack"
# Rows per packed chunk: a reader's requests per array grow by one per 16,384 samples (nuScenes: 3,
# concurrent), and the commit holds one chunk of one array (12 MiB for the (N, 6, 4, 4) float64 ones, ~3x
# that while zarr encodes it) whatever the sample count.
PACK_ROWS = 16_384


def pack_names(attrs: Any) -> tuple[str, ...]:
    """The small (not sharded) per-sample arrays of a store with these root attributes."""
    return tuple(s.name for s in per_sample(has_flow(attrs), grid_shape(attrs), camera_count(attrs)) if not s.sharded)


def packed_crc(data: np.ndarray) -> int:
    """crc32 of an array's C-order bytes: the check a reader runs on a packed copy."""
    return zlib.crc32(np.ascontiguousarray(data).tobytes())


def drop_pack(root: zarr.Group) -> None:
    """Mark the packed copies stale before writing any small array (readers then read the chunks)."""
    if PACK_ATTR in root.attrs:
        root.attrs.put({k: v for k, v in root.attrs.items() if k != PACK_ATTR})


def write_pack(root: zarr.Group) -> None:
    """Copy every small per-sample array into `pack/<name>` (chunks of `PACK_ROWS` samples), then stamp the root.

    One chunk of one array is in memory at a time: each array is written with its crc32 (computed as its
    chunks are read), and the generation (a digest of all of them) is put on every packed array
    afterwards, so the client's peak at the final commit does not grow with the samples, and each small
    array is read once. The root attribute is
    written last: a run killed half-way leaves readers on the chunks (a packed array's generation must
    equal the root's). The caller rewrites the consolidated metadata afterwards (the build's final commit
    does)."""
    drop_pack(root)
    facts: dict[str, tuple[str, tuple[int, ...], int]] = {}
    packed = []
    for name in pack_names(root.attrs):
        src = root[name]
        rows = max(1, min(PACK_ROWS, src.shape[0]))
        arr = root.create_array(f"{PACK_GROUP}/{name}", shape=src.shape, dtype=src.dtype,
                                chunks=(rows, *src.shape[1:]) if src.size else None, compressors=ZstdCodec(level=3),
                                overwrite=True, attributes={"generation": "", "crc32": 0})
        crc = 0
        for i0 in range(0, src.shape[0], rows):  # one chunk of rows in memory at a time
            values = np.asarray(src[i0:i0 + rows])
            # running crc over the C-order bytes of consecutive row chunks = packed_crc of the whole array
            crc = zlib.crc32(memoryview(np.ascontiguousarray(values)).cast("B"), crc)
            arr[i0:i0 + rows] = values
        arr.attrs["crc32"] = crc
        facts[name] = (np.dtype(src.dtype).str, tuple(src.shape), crc)
        packed.append(arr)
    generation = _generation(facts)
    for arr in packed:
        arr.attrs["generation"] = generation
    root.attrs[PACK_ATTR] = {"generation": generation}


def _generation(facts: dict[str, tuple[str, tuple[int, ...], int]]) -> str:
    """A digest of the packed content (each array's dtype, shape and crc32): equal stores get equal
    attributes (a resumed build's store is identical to an uninterrupted one), and copies from another
    commit carry another generation."""
    h = hashlib.sha256()
    for name, (dtype, shape, crc) in sorted(facts.items()):
        h.update(f"{name} {dtype} {shape} {crc};".encode())
    return h.hexdigest()[:32]
