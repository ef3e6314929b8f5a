"""One writer per run folder: an exclusive `fcntl` lock on `<out>/.lock`, held for the whole run.

The kernel releases the lock when the process dies (even by SIGKILL), so a stale lock never blocks
a restart. A second trainer on the same `--out` stops with one line naming the holder's PID and host.
Holding the lock also makes it safe to delete the temporaries an interrupted save left behind.
"""

from __future__ import annotations

import fcntl
import os
import socket
from pathlib import Path

from occdata.errors import OccDataError
from occdata.fileio import current_umask, remove_stale_temps

__all__ = ["RunFolderBusy", "RunLock"]

LOCK_NAME = ".lock"


class RunFolderBusy(OccDataError):
    """Another process holds the run folder's lock."""


class RunLock:
    """`with RunLock(out):` the exclusive writer of `out` (created if missing); stale `.tmp` files removed."""

    def __init__(self, out: str | Path) -> None:
        self.out = Path(out)
        self._fd: int | None = None
        self.removed: list[Path] = []

    def __enter__(self) -> RunLock:
        path = self.out / LOCK_NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666 & ~current_umask())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 256, 0).decode(errors="replace").split()
            os.close(fd)
            who = f"PID {holder[0]} on host {holder[1]}" if len(holder) >= 2 else "another process"
            raise RunFolderBusy(f"{self.out} is in use by another fastocc train ({who}); wait for it to finish "
                                "or choose another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        self._fd = fd
        self.removed = remove_stale_temps(self.out)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the lock
            self._fd = None
