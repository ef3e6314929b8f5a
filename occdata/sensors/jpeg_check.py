"""Decode a JPEG and treat every libjpeg warning as corruption (no torch).

libjpeg recovers from damaged entropy-coded data (a stream cut short with an EOI marker appended,
zeroed data, a bad Huffman code) by filling the rest of the image with grey; it prints one warning
line on stderr and OpenCV returns the image as if nothing happened. That line is the only signal, so
the decode runs with file descriptor 2 pointed at a private scratch file: anything written there
rejects the image, and the message is returned so that the caller can name the file.

The redirection is process-wide for the few microseconds of the decode and is serialised by a lock;
another thread writing to stderr at that moment would have its text taken for a warning (a false
alarm on the safe side). The build calls this from its worker processes.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from typing import IO

import cv2
import numpy as np

__all__ = ["decode_jpeg_checked"]

_lock = threading.Lock()
_scratch: tuple[int, IO[bytes]] | None = None  # (pid, file): a forked child makes its own


def _scratch_file() -> IO[bytes]:
    global _scratch
    if _scratch is None or _scratch[0] != os.getpid():
        _scratch = (os.getpid(), tempfile.TemporaryFile())  # noqa: SIM115 - lives as long as the process
    return _scratch[1]


def decode_jpeg_checked(data: bytes | np.ndarray, flag: int = cv2.IMREAD_COLOR) -> tuple[np.ndarray | None, str]:
    """`cv2.imdecode(data, flag)` and the decoder's warning text ("" when it printed nothing).

    Returns `(image or None, warning)`; a non-empty warning means the stream is damaged even if an
    image came back. With `cv2.IMREAD_REDUCED_*_8` the whole entropy-coded stream is still read, so
    the check is as strict as a full decode at a fraction of the cost.
    """
    buf = np.frombuffer(data, dtype=np.uint8) if isinstance(data, bytes) else data
    with _lock:
        scratch = _scratch_file()
        fd = scratch.fileno()
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        with contextlib.suppress(Exception):
            sys.stderr.flush()  # Python's own buffered text must not land in the scratch file
        try:
            saved: int | None = os.dup(2)
        except OSError:  # no stderr at all (a daemon): capture anyway, close it again afterwards
            saved = None
        try:
            os.dup2(fd, 2)
            img = cv2.imdecode(buf, flag)
        finally:
            if saved is None:
                os.close(2)
            else:
                os.dup2(saved, 2)
                os.close(saved)
        size = os.fstat(fd).st_size
        text = os.pread(fd, min(size, 400), 0).decode("utf-8", "replace") if size else ""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return img, (lines[0] if lines else ("decoder warning" if size else ""))
