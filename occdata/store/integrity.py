"""Is what a reader got from the store what the builder wrote? Chunk presence and checksums.

zarr returns the fill value for a chunk that is not stored, without a word. The builder stores
chunks as zarr's default `write_empty_chunks=False` does (`occdata.store.blocks._write_rows`), so a
chunk that holds only fill values is legitimately absent (labels of unlabelled samples,
`labels/present` of an unlabelled block). A stored per-sample checksum tells the two cases apart:
an absent chunk is fine exactly when every committed sample in it has the checksum of a fill row for
that array. Rules:

- checksummed per-sample arrays: chunk (or shard) absent -> each committed sample in it must
  have the fill row's checksum. A missing inner chunk inside a present shard reads as fill too;
  it is caught where the rows are read, by `check_rows` (crc32 runs at ~3 GB/s, so readers of the
  big arrays check every row they return).
- flat arrays (`images/jpeg`, `depth/uvd`): an absent chunk under a committed sample's non-empty
  range is corruption (JPEG bytes and depths > 0 are never a whole chunk of zeros).
- `status/checksum`: absent under a committed sample is corruption.
- `status/state` (the commit flag; pending = 0 = its fill value): the builder writes every state
  chunk when it creates (or resumes) a store, so there an absent state chunk comes from damage.
  Stores from before that rule committed blocks in sample order with no chunk for the pending tail,
  and the check cannot tell the two apart: an absent state chunk is corruption when the store says
  it is complete or when a later state chunk is stored; otherwise those samples count as pending.

Listings are one `list_prefix` per array, cached per `StoreIntegrity`.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import zarr
from zarr.core.sync import collect_aiterator

from occdata.errors import OccDataError
from occdata.fileio import is_temp_name
from occdata.store.layout import (
    FLAT_ARRAYS,
    FLAT_OF_OFFSETS,
    FLOW,
    STATE_PENDING,
    ArraySpec,
    camera_count,
    checksummed_names,
    grid_shape,
    has_flow,
    per_sample,
    token_str,
)

__all__ = ["CorruptStoreError", "StoreIntegrity", "crc_rows"]


class CorruptStoreError(OccDataError):
    """Store data that does not match what the builder committed; the message names the sample."""


def crc_rows(data: np.ndarray) -> np.ndarray:
    """`(n,) uint32` crc32 of each row's C-order bytes (the build-time per-sample checksum)."""
    return np.array([zlib.crc32(np.ascontiguousarray(row).tobytes()) for row in data], dtype=np.uint32)


def _specs(attrs: dict[str, Any]) -> dict[str, ArraySpec]:
    """Every per-sample array of a store with these attributes (its label grid's shapes)."""
    return {s.name: s for s in (*per_sample(False, grid_shape(attrs), camera_count(attrs)), FLOW)}


class StoreIntegrity:
    """Presence and checksum checks over one open zarr group (read-only use)."""

    def __init__(self, group: zarr.Group, attrs: dict[str, Any] | None = None,
                 packed: Callable[[str], np.ndarray | None] | None = None) -> None:
        """`packed(name)`: a small array the reader holds or reads in one request (its checked packed copy),
        or None: then its chunks are read."""
        self.group = group
        self._packed = packed
        self.attrs = dict(group.attrs) if attrs is None else attrs
        self.names = checksummed_names(has_flow(self.attrs))
        self._spec = _specs(self.attrs)
        self._keys: dict[str, set[str]] = {}
        self._checksums: np.ndarray | None = None
        self._tokens: np.ndarray | None = None
        self._fill_crc: dict[str, int] = {}

    # --- listings --------------------------------------------------------------------------------
    def _chunk_rows(self, name: str) -> int:
        return int(self.group[name].metadata.chunk_grid.chunk_shape[0])

    def _chunk_key(self, name: str, k: int, arr: zarr.Array | None = None) -> str:
        arr = self.group[name] if arr is None else arr  # a group lookup may be a request: pass arr in loops
        return f"{arr.path}/" + arr.metadata.encode_chunk_key((k,) + (0,) * (arr.ndim - 1))

    def stored_keys(self, name: str) -> set[str]:
        if name not in self._keys:
            arr = self.group[name]
            try:
                keys = collect_aiterator(arr.store.list_prefix(f"{arr.path}/c"))
            except Exception as exc:  # noqa: BLE001 - a store that cannot be listed is reported plainly
                raise OccDataError(f"cannot list the chunks of {name}: {exc}") from None
            self._keys[name] = {k for k in keys if not is_temp_name(k)}
        return self._keys[name]

    def absent_chunks(self, name: str) -> np.ndarray:
        """`(n_chunks,) bool` along the sample (row) axis: True where the chunk/shard file is absent."""
        arr = self.group[name]
        n = math.ceil(arr.shape[0] / self._chunk_rows(name)) if arr.shape[0] else 0
        keys = self.stored_keys(name)
        return np.array([self._chunk_key(name, k, arr) not in keys for k in range(n)], dtype=bool)

    def present_chunks(self, name: str) -> np.ndarray:
        """`(k,) int64`, sorted: the indices along the row axis of `name`'s stored chunk/shard files,
        parsed from its listing (one pass over the keys, no key made per possible chunk)."""
        arr = self.group[name]
        head = self._chunk_key(name, 0, arr)[: -len("0" + "/0" * (arr.ndim - 1))]  # e.g. "images/jpeg/c/"
        sep = self._chunk_key(name, 0, arr)[len(head) + 1 :][:1] or "/"
        found = []
        for key in self.stored_keys(name):
            if key.startswith(head):
                first = key[len(head) :].split(sep, 1)[0]
                if first.isdigit():
                    found.append(int(first))
        return np.unique(np.array(found, dtype=np.int64))

    def chunk_rows(self, name: str) -> int:
        """Rows (samples; elements of a flat array) per chunk/shard file of `name`."""
        return self._chunk_rows(name)

    def read_small(self, name: str) -> np.ndarray:
        """A small array whole (its packed copy where the reader holds one); `CorruptStoreError` if unreadable."""
        return self._read(name)

    def chunk_file(self, name: str, row: int) -> str:
        return self._chunk_key(name, row // self._chunk_rows(name))

    # --- helpers ---------------------------------------------------------------------------------
    def checksums(self) -> np.ndarray:
        if self._checksums is None:
            self._checksums = self._read("status/checksum")
        return self._checksums

    def token(self, i: int) -> str:
        try:
            if self._tokens is None:
                self._tokens = self._read("sample/token")
            return token_str(self._tokens[i])
        except Exception:  # noqa: BLE001 - the token array itself may be the damaged one
            return "?"

    def fill_crc(self, name: str) -> int:
        if name not in self._fill_crc:
            s = self._spec[name]
            self._fill_crc[name] = zlib.crc32(np.full(s.shape, s.fill, dtype=s.dtype).tobytes())
        return self._fill_crc[name]

    def _read(self, name: str) -> np.ndarray:
        packed = self._packed(name) if self._packed is not None else None
        if packed is not None:
            return packed
        try:
            return np.asarray(self.group[name][:])
        except Exception as exc:  # noqa: BLE001 - codec errors surface as many types
            raise CorruptStoreError(f"store array {name} is unreadable ({type(exc).__name__}: {exc})") from None

    def _corrupt(self, i: int, name: str, what: str) -> CorruptStoreError:
        return CorruptStoreError(f"corrupt store: sample {i} ({self.token(i)}): {name}: {what}")

    # --- checks ------------------------------------------------------------------------------------
    def read_state(self) -> np.ndarray:
        """`status/state`, checked: raises `CorruptStoreError` where a state chunk went missing (a
        current packed copy is checked by its crc32 instead: no listing)."""
        packed = self._packed("status/state") if self._packed is not None else None
        if packed is not None:
            return packed
        state = self._read("status/state")
        absent = self.absent_chunks("status/state")
        if absent.any():
            rows = self._chunk_rows("status/state")
            later = np.flatnonzero(~absent)
            for k in np.flatnonzero(absent):
                if self.attrs.get("complete") or (later > k).any():
                    i0, i1 = k * rows, min((k + 1) * rows, len(state)) - 1
                    raise CorruptStoreError(
                        f"corrupt store: the commit flags of samples {i0}..{i1} are missing "
                        f"({self._chunk_key('status/state', int(k))}); rebuild, or delete the file and "
                        f"rerun `occdata build --resume` to rebuild those samples"
                    )
        return state

    def problems_absent(self, name: str, state: np.ndarray) -> list[tuple[int, str]]:
        """(sample, reason) for committed samples that an absent chunk of `name` makes wrong."""
        committed = state != STATE_PENDING
        if name in FLAT_ARRAYS:  # only the chunks under committed offsets: the address space is sparse
            return self._flat_absent(name, committed) if committed.any() else []
        absent = self.absent_chunks(name)
        if not absent.any() or not committed.any():
            return []
        out: list[tuple[int, str]] = []
        rows = self._chunk_rows(name)
        for k in np.flatnonzero(absent):
            idx = [i for i in range(k * rows, min((k + 1) * rows, len(state))) if committed[i]]
            if not idx:
                continue
            key = self._chunk_key(name, int(k))
            if name == "status/checksum" or name not in self.names:
                out += [(i, f"chunk {key} is missing") for i in idx]
                continue
            col = self.names.index(name)
            stored = self.checksums()[idx, col]
            bad = stored != self.fill_crc(name)
            out += [(i, f"chunk {key} is missing") for i, b in zip(idx, bad, strict=True) if b]
        return out

    def _flat_absent(self, name: str, committed: np.ndarray) -> list[tuple[int, str]]:
        """(sample, reason) for committed samples with a flat-array chunk under their offsets absent."""
        rows = self._chunk_rows(name)
        off_name = next(o for o, f in FLAT_OF_OFFSETS.items() if f == name)
        off = self._read(off_name)
        keys = self.stored_keys(name)
        arr = self.group[name]
        n_chunks = math.ceil(arr.shape[0] / rows)
        out: list[tuple[int, str]] = []
        for i in np.flatnonzero(committed):
            for start, n in off[i]:
                if n <= 0:
                    continue
                gone = [k for k in range(int(start) // rows, min((int(start) + int(n) - 1) // rows + 1, n_chunks))
                        if self._chunk_key(name, k, arr) not in keys]
                if gone:
                    out.append((int(i), f"chunk {self._chunk_key(name, gone[0])} is missing"))
                    break
        return out

    def check_present(self, name: str, state: np.ndarray) -> None:
        """Raise `CorruptStoreError` naming the first committed sample an absent chunk hides."""
        bad = self.problems_absent(name, state)
        if bad:
            i, why = bad[0]
            more = f" (and {len(bad) - 1} more samples)" if len(bad) > 1 else ""
            raise self._corrupt(i, name, why + more)

    def check_rows(self, name: str, indices: Iterable[int], rows: Iterable[np.ndarray | bytes]) -> None:
        """Compare rows read for committed samples with their build-time checksums.

        `rows` are per-sample arrays (no sample axis) or, for flat arrays, the sample's bytes (its
        camera slices concatenated). Raises `CorruptStoreError` naming the sample.
        """
        col = self.names.index(name)
        sums = self.checksums()
        for i, row in zip(indices, rows, strict=True):
            data = row if isinstance(row, bytes) else np.ascontiguousarray(row).tobytes()
            if zlib.crc32(data) != int(sums[i, col]):
                raise self._corrupt(
                    int(i), name, "data differs from what was built (checksum mismatch: a missing or "
                    "damaged chunk); run `occdata verify`"
                )
