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

__all__ = ["TEXT_ERRORS", "Spill"]

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
