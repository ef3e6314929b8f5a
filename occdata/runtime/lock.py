"""One writer per store: an advisory `fcntl` lock on `<store>.lock`, next to the store.

The lock file sits beside the store (not inside it) because a new store only appears, by an atomic
rename, once its layout is complete. It is kept after the writer ends: deleting a lock file races
with a second writer that has it open. The kernel drops the lock when the holder exits, even on
kill -9, so a stale file never blocks anyone; its content (pid, host, start time, command) only
serves the message of the writer that is refused.

An object store (s3://...) has no advisory lock. There the lock is twofold: the same `fcntl` lock on
a local file named after the URL (two writers on one host), and a lease object `<store>.lock`
holding the holder's host, pid and a heartbeat renewed every `LEASE_RENEW_S`. A writer on another
host is refused while the lease is younger than `LEASE_STALE_S`; on the holder's own host a lease
whose local lock is free belongs to a dead process and is taken over at once.
"""

from __future__ import annotations

import datetime
import fcntl
import hashlib
import json
import os
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from occdata.errors import OccDataError

__all__ = ["LEASE_RENEW_S", "LEASE_STALE_S", "StoreLockedError", "lock_path", "store_lock"]

LEASE_RENEW_S = 20.0
LEASE_STALE_S = 90.0


class StoreLockedError(OccDataError):
    """Another process is writing the store."""


def lock_path(store: str | Path) -> Path:
    """The local lock file: beside a local store; for a URL, a file named after it in the temp folder."""
    if "://" in str(store):
        digest = hashlib.sha256(str(store).rstrip("/").encode()).hexdigest()[:24]
        return Path(tempfile.gettempdir()) / "occdata-locks" / f"{digest}.lock"
    p = Path(store)
    return p.with_name(p.name + ".lock")


@contextmanager
def store_lock(store: str | Path, command: str) -> Iterator[None]:
    """Hold the store's write lock for the `with` body; refuse at once if another writer holds it.

    A URL store also takes the lease object `<store>.lock` (see the module docstring).
    """
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
        if "://" in str(store):
            with _lease(str(store).rstrip("/") + ".lock", info):
                yield
        else:
            yield
    finally:
        os.close(fd)  # releases the flock


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text() or "{}")
        return f"`occdata {info['command']}`, pid {info['pid']} on host {info['host']}, started {info['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"


@contextmanager
def _lease(url: str, info: dict[str, object]) -> Iterator[None]:
    """Hold the lease object `url` (the local lock is already held) for the `with` body."""
    from occdata.runtime.storage import read_bytes, remove_tree, write_atomic

    raw = read_bytes(url)
    if raw is not None:
        try:
            held = json.loads(raw)
            age = time.time() - float(held["beat"])
            other_host = held["host"] != info["host"]
        except (ValueError, KeyError, TypeError):
            held, age, other_host = {}, LEASE_STALE_S, True
        if other_host and age < LEASE_STALE_S:
            raise StoreLockedError(
                f"{url[:-5]} is being written from host {held.get('host')} (pid {held.get('pid')}, `occdata "
                f"{held.get('command')}`, heartbeat {age:.0f} s ago); wait for it to finish, or delete {url} "
                f"if that writer is gone (a lease without heartbeat expires after {LEASE_STALE_S:.0f} s)")
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(LEASE_RENEW_S):
            try:
                write_atomic(url, json.dumps({**info, "beat": time.time()}).encode())
            except Exception:  # noqa: BLE001, S110 - the store is unreachable: the build reports that itself
                pass

    write_atomic(url, json.dumps({**info, "beat": time.time()}).encode())
    thread = threading.Thread(target=beat, name="occdata-lease", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=5)
        try:
            remove_tree(url)
        except OSError:
            pass
