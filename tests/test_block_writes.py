"""The block writer's shortcut around zarr's all-fill scan stores exactly what zarr's default write
stores (`write_empty_chunks=False`): the same chunk keys and bytes, for rows that are all data, all
fill, mixed, and not aligned to the chunks; zarr's own default write is the truth here."""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest
import zarr

from occdata.store.blocks import _write_rows


def _stored(path: Path) -> dict[str, bytes]:
    return {str(f.relative_to(path)): f.read_bytes() for f in sorted(path.rglob("*")) if f.is_file()
            and f.name != "zarr.json"}


def _array(root: Path, sharded: bool) -> zarr.Array:
    g = zarr.open_group(root, mode="w")
    return g.create_array("labels/semantics", shape=(12, 5, 3), dtype="uint8", fill_value=255,
                          chunks=(1, 5, 3) if sharded else (4, 5, 3), shards=(4, 5, 3) if sharded else None,
                          compressors=zarr.codecs.ZstdCodec(level=1))


def _kind(rows: np.ndarray, fill: int) -> str:
    """What `convert_block` derives from the rows' checksums."""
    fill_sum = zlib.crc32(np.full(rows.shape[1:], fill, dtype=rows.dtype).tobytes())
    is_fill = np.array([zlib.crc32(r.tobytes()) == fill_sum for r in rows])
    return "fill" if is_fill.all() else "mixed" if is_fill.any() else "data"


@pytest.mark.parametrize("sharded", [True, False])
@pytest.mark.parametrize(("i0", "i1", "fill_rows"), [
    (4, 8, []),             # all data, aligned
    (4, 8, [0, 1, 2, 3]),   # all fill over stored data: zarr deletes the chunk
    (8, 12, [1]),           # mixed: the fill row's inner chunk stays absent
    (2, 6, [0, 1, 2, 3]),   # all fill, not aligned: written through zarr
    (0, 12, list(range(12))),
])
def test_block_rows_store_what_zarrs_default_write_stores(tmp_path: Path, sharded: bool, i0: int, i1: int,
                                                          fill_rows: list[int]) -> None:
    rng = np.random.default_rng(0)
    before = rng.integers(0, 200, size=(12, 5, 3), dtype=np.uint8)
    rows = rng.integers(0, 200, size=(i1 - i0, 5, 3), dtype=np.uint8)
    rows[fill_rows] = 255
    kind = _kind(rows, 255)
    assert kind == ("fill" if len(fill_rows) == i1 - i0 else "mixed" if fill_rows else "data")
    stored = {}
    for name, shortcut in (("zarr", False), ("ours", True)):
        arr = _array(tmp_path / name, sharded)
        arr[:] = before
        if shortcut:
            _write_rows([(arr, i0, i1, rows)], None, {"labels/semantics": kind})
        else:
            arr[i0:i1] = rows
        stored[name] = _stored(tmp_path / name)
        np.testing.assert_array_equal(arr[i0:i1], rows)
    assert stored["ours"] == stored["zarr"]
    assert bool(stored["zarr"]) == (len(fill_rows) < 12)  # every chunk deleted only in the last case
