"""One writer per store: an advisory `fcntl` lock on `<store>.lock`, next to the store.

The lock file sits beside the store (not inside it) because a new store only appears, by an atomic
rename, once its layout is complete. It is kept after the writer ends: deleting a lock file races
with a second writer that has it open. The kernel drops the lock when the holder exits, even on
kill -9, so a stale file never blocks anyone; its content (pid, host, start time, command) only
serves the message of the writer that is refused.
"""

from __future__ import annotations

import datetime
import fcntl
import json
import os
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from occdata.errors import OccDataError

__all__ = ["StoreLockedError", "lock_path", "store_lock"]


class StoreLockedError(OccDataError):
    """Another process is writing the store."""


def lock_path(store: str | Path) -> Path:
    p = Path(store)
    return p.with_name(p.name + ".lock")


@contextmanager
def store_lock(store: str | Path, command: str) -> Iterator[None]:
    """Hold the store's write lock for the `with` body; refuse at once if another writer holds it.

    Remote (fsspec URL) stores are not locked: there is no portable lock there.
    """
    if "://" in str(store):
        yield
        return
    path = lock_path(store)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise OccDataError(f"cannot create the lock file {path}: {exc.strerror}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise StoreLockedError(f"{store} is being written by another process ({_holder(path)}); wait for it "
                                   f"to finish or stop it (lock file {path})") from None
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": command,
                "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the flock


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text() or "{}")
        return f"`occdata {info['command']}`, pid {info['pid']} on host {info['host']}, started {info['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"
