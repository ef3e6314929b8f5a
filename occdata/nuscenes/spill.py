"""Blobs kept on disk and read back one at a time: what a client must keep for every sample, but reads a
sample at a time (packed keyframe records, a sample's boxes), held in an unnamed temporary file instead
of memory. In memory a blob costs its end offset (8 bytes); reading it back is one `os.pread`, served
from the page cache while the machine has memory to spare and from disk when it has not.

The file is made in the temporary folder (`TMPDIR`), already unlinked: nothing is left behind by a
crash or a kill. A `Spill` is not pickled: what travels to a task is the records it reads.
"""

from __future__ import annotations

import os
import tempfile
import threading
import weakref
from array import array
from typing import Any

import numpy as np

__all__ = ["TEXT_ERRORS", "BucketSpill", "Spill"]

# How blobs encode their texts: UTF-8, a lone surrogate (JSON "\ud800", which the tables allow) kept.
TEXT_ERRORS = "surrogatepass"

_BUFFER = 1 << 20  # appends are written in batches of about this many bytes


class Spill:
    """`add(blob)` appends blob k (k = 0, 1, ...); `get(k)` reads it back; `len()` counts them;
    `flush()` writes the tail still in memory (done by `get` when it needs it); `nbytes()` is the
    memory held (the offsets and the unwritten tail)."""

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile(prefix="occdata-spill-")
        weakref.finalize(self, self._file.close)  # closed with the spill, not left to the file's own finaliser
        self._ends = array("Q")
        self._tail = bytearray()  # added, not yet written
        self._written = 0
        self._lock = threading.Lock()  # a flush racing a read from another thread

    def __len__(self) -> int:
        return len(self._ends)

    def add(self, blob: bytes) -> None:
        self._tail += blob
        self._ends.append(self._written + len(self._tail))
        if len(self._tail) >= _BUFFER:
            self.flush()

    def flush(self) -> None:
        with self._lock:
            view = memoryview(self._tail)
            while view:  # a regular file takes it whole; a short write is continued, not lost
                n = os.pwrite(self._file.fileno(), view, self._written)
                self._written += n
                view = view[n:]
            self._tail = bytearray()

    def get(self, k: int) -> bytes:
        start = self._ends[k - 1] if k else 0
        end = self._ends[k]
        if end > self._written:
            self.flush()
        data = os.pread(self._file.fileno(), end - start, start)
        if len(data) != end - start:  # the file shrank under us (another process truncated it)
            raise OSError(f"spill file: read {len(data)} of {end - start} bytes of blob {k}")
        return data

    def nbytes(self) -> int:
        return self._ends.itemsize * len(self._ends) + len(self._tail)

    def __reduce__(self) -> Any:
        raise TypeError("a Spill is not pickled: send the records it holds")


BUCKETS = 64  # a BucketSpill's buckets, by the top 6 bits of a hash


def bucket_of(hashes: np.ndarray) -> np.ndarray:
    """`(n,) int64` hashes -> `(n,) uint64` their bucket, 0..63 (the top 6 bits: str hashes are uniform)."""
    return np.asarray(hashes, dtype=np.int64).view(np.uint64) >> np.uint64(58)


class BucketSpill:
    """Rows of a numpy structured `dtype`, kept on disk in `BUCKETS` buckets by the top bits of the
    int64 hash field `key`: `add(rows)`; `bucket(b)` reads bucket b's rows back, in the order added.
    Memory holds the rows not yet written (`in_memory` at most) and 8 bytes a written blob, so a pass
    over the buckets holds one bucket (1/64 of the rows) however many rows there are."""

    def __init__(self, dtype: np.dtype, key: str, in_memory: int = 1 << 16) -> None:
        self._dtype, self._key, self._in_memory = np.dtype(dtype), key, in_memory
        self._pending: list[np.ndarray] = []
        self._n_pending = 0
        self._spill = Spill()
        self._blobs: list[array] = [array("q") for _ in range(BUCKETS)]

    def add(self, rows: np.ndarray) -> None:
        self._pending.append(np.asarray(rows, dtype=self._dtype))
        self._n_pending += len(rows)
        if self._n_pending >= self._in_memory:
            self._write()

    def _write(self) -> None:
        if not self._n_pending:
            return
        rows = np.concatenate(self._pending)
        self._pending, self._n_pending = [], 0
        which = bucket_of(rows[self._key])
        order = np.argsort(which, kind="stable")  # stable: a bucket keeps the order rows were added in
        ends = np.searchsorted(which[order], np.arange(1, BUCKETS + 1, dtype=np.uint64))
        for b, part in enumerate(np.split(rows[order], ends[:-1])):
            if len(part):
                self._blobs[b].append(len(self._spill))
                self._spill.add(part.tobytes())

    def bucket(self, b: int) -> np.ndarray:
        """`(k,) dtype` bucket b's rows, in the order they were added (a new array)."""
        self._write()
        parts = [np.frombuffer(self._spill.get(i), self._dtype) for i in self._blobs[b]]
        return np.concatenate(parts) if parts else np.zeros(0, self._dtype)

    def __reduce__(self) -> Any:
        raise TypeError("a BucketSpill is not pickled")
