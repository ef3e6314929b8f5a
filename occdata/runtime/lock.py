"""One writer per store: an advisory `fcntl` lock on `<store>.lock`, next to the store.

The lock file sits beside the store (not inside it) because a new store only appears, by an atomic
rename, once its layout is complete. It is kept after the writer ends: deleting a lock file races
with a second writer that has it open. The kernel drops the lock when the holder exits, even on
kill -9, so a stale file never blocks anyone; its content (pid, host, start time, command) only
serves the message of the writer that is refused.

An object store (s3://...) has no advisory lock. There the lock is twofold: the same `fcntl` lock on
a local file named after the URL (two writers on one host), and a lease object `<store>.lock`
holding the holder's host, pid, a nonce and a heartbeat renewed every `LEASE_RENEW_S`. A writer on
another host is refused while the lease is younger than `LEASE_STALE_S`; on the holder's own host a
lease whose local lock is free belongs to a dead process and is taken over.

On S3 every write of the lease is conditional, so one host holds it: it is created with
`If-None-Match: *` (of two writers racing, one gets 412), taken over and renewed with `If-Match:
<the ETag last seen>`, and deleted with `If-Match: <our ETag>` (never another holder's lease). A
renewal that finds the lease changed, or none that succeeded for `LEASE_STALE_S - LEASE_RENEW_S`
(others may take it over soon), loses the lease: `StoreLock.check()` then raises `LeaseLostError`,
which the writer polls (`occdata build` with its stop signals) and `store_lock` raises at the end.
Other fsspec stores have no conditional request known here: the lease is created exclusively where
the filesystem implements `pipe_file(mode="create")` and checked-then-written otherwise, renewals and
the delete compare the content first (a small window remains), and a warning says so.
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
import uuid
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from occdata.errors import OccDataError, OccDataWarning

__all__ = ["LEASE_RENEW_S", "LEASE_STALE_S", "LeaseLostError", "StoreLock", "StoreLockedError", "lock_path",
           "store_lock"]

LEASE_RENEW_S = 20.0
LEASE_STALE_S = 90.0


class StoreLockedError(OccDataError):
    """Another process is writing the store."""


class LeaseLostError(OccDataError):
    """The lease of a remote store lapsed, or another writer holds it now: this writer must stop."""


class StoreLock:
    """What `store_lock` yields. `check()` raises `LeaseLostError` once a remote store's lease is no
    longer this writer's (a no-op for a local store, whose lock the kernel holds)."""

    def __init__(self, lease: _Lease | None = None) -> None:
        self._lease = lease

    def check(self) -> None:
        if self._lease is not None:
            self._lease.check()


def lock_path(store: str | Path) -> Path:
    """The local lock file: beside a local store; for a URL, a file named after it in the temp folder."""
    if "://" in str(store):
        digest = hashlib.sha256(str(store).rstrip("/").encode()).hexdigest()[:24]
        return Path(tempfile.gettempdir()) / "occdata-locks" / f"{digest}.lock"
    p = Path(store)
    return p.with_name(p.name + ".lock")


@contextmanager
def store_lock(store: str | Path, command: str) -> Iterator[StoreLock]:
    """Hold the store's write lock for the `with` body; refuse at once if another writer holds it.

    A URL store also takes the lease object `<store>.lock` (see the module docstring); a lease lost
    during the body raises `LeaseLostError` from `StoreLock.check()` and, when the body ends, here.
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
            lease = _Lease(str(store).rstrip("/") + ".lock", info)
            lease.acquire()
            try:
                yield StoreLock(lease)
            finally:
                lease.release()
            lease.check()  # reached when the body ended by itself: a lease lost meanwhile fails the run
        else:
            yield StoreLock()
    finally:
        os.close(fd)  # releases the flock


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text() or "{}")
        return f"`occdata {info['command']}`, pid {info['pid']} on host {info['host']}, started {info['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"


class _Taken(Exception):
    """A conditional write or delete found the lease object changed or gone since this writer saw it."""


class _S3Object:
    """The lease object on S3, every write conditional (`If-None-Match: *` to create, `If-Match: <ETag>`
    to replace and to delete), passed by s3fs to botocore as they are; moto implements all three."""

    exclusive = True
    _CONFLICT = frozenset({"PreconditionFailed", "ConditionalRequestConflict", "NoSuchKey", "404", "409", "412"})

    def __init__(self, fs: Any, path: str) -> None:
        self.fs, self.path = fs, path
        self.bucket, self.key, _ = fs.split_path(path)

    def _call(self, op: str, **kw: Any) -> dict[str, Any]:
        try:
            return self.fs.call_s3(op, Bucket=self.bucket, Key=self.key, **kw)
        except OSError as exc:  # s3fs translates botocore's ClientError and keeps it as the cause
            code = (getattr(exc.__cause__, "response", None) or {}).get("Error", {}).get("Code")
            if isinstance(exc, FileNotFoundError | FileExistsError) or code in self._CONFLICT:
                raise _Taken(code or type(exc).__name__) from None
            raise

    def create(self, data: bytes) -> str:
        return str(self._call("put_object", Body=data, IfNoneMatch="*")["ETag"])

    def replace(self, data: bytes, tag: str) -> str:
        return str(self._call("put_object", Body=data, IfMatch=tag)["ETag"])

    def read(self) -> tuple[bytes, str] | None:
        try:  # the ETag first: the content read next is the same or newer, so a replace on it is safe
            tag = str(self._call("head_object")["ETag"])
            return bytes(self.fs.cat_file(self.path)), tag
        except (_Taken, FileNotFoundError):
            return None

    def delete(self, tag: str) -> None:
        self._call("delete_object", IfMatch=tag)


class _PlainObject:
    """The lease object on a store without a conditional request known here: `pipe_file(mode="create")`
    (exclusive where the filesystem implements it, else checked then written); a replace or delete
    compares the content first, so two writers acting at the same instant can both succeed."""

    exclusive = False

    def __init__(self, fs: Any, path: str) -> None:
        self.fs, self.path = fs, path

    def create(self, data: bytes) -> str:
        try:
            self.fs.pipe_file(self.path, data, mode="create")
        except FileExistsError:
            raise _Taken("exists") from None
        return hashlib.sha256(data).hexdigest()

    def read(self) -> tuple[bytes, str] | None:
        try:
            data = bytes(self.fs.cat_file(self.path))
        except FileNotFoundError:
            return None
        return data, hashlib.sha256(data).hexdigest()

    def _expect(self, tag: str) -> None:
        held = self.read()
        if held is None or held[1] != tag:
            raise _Taken("changed")

    def replace(self, data: bytes, tag: str) -> str:
        self._expect(tag)
        self.fs.pipe_file(self.path, data)
        return hashlib.sha256(data).hexdigest()

    def delete(self, tag: str) -> None:
        self._expect(tag)
        self.fs.rm_file(self.path)


def _lease_object(url: str) -> _S3Object | _PlainObject:
    import fsspec

    try:
        fs, path = fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as exc:
        raise OccDataError(f"cannot open {url}: {exc} (s3:// needs `pip install occdata[s3]`)") from None
    protocols = (fs.protocol,) if isinstance(fs.protocol, str) else tuple(fs.protocol)
    if {"s3", "s3a"} & set(protocols):
        return _S3Object(fs, path)
    warnings.warn(OccDataWarning(
        f"{url}: {protocols[0]}:// has no conditional write known to occdata, so its write lease is checked, "
        "then written: two writers starting at the same moment could both take it"), stacklevel=4)
    return _PlainObject(fs, path)


def _lapse_s() -> float:
    """Without a renewal for this long the lease counts as lost: others take it over at LEASE_STALE_S."""
    return LEASE_STALE_S - LEASE_RENEW_S


class _Lease:
    """This writer's hold on the lease object `url` (the local lock is already held)."""

    def __init__(self, url: str, info: dict[str, object]) -> None:
        self.url, self.store = url, url[: -len(".lock")]
        self.info = {**info, "nonce": uuid.uuid4().hex}  # two leases of one host and pid still differ
        self.obj = _lease_object(url)
        self.tag = ""
        self.last_ok = time.monotonic()
        self.last_error = ""  # the latest failed renewal's "Type: message" ("" while renewals succeed)
        self.lost: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="occdata-lease", daemon=True)

    def _body(self) -> bytes:
        return json.dumps({**self.info, "beat": time.time()}).encode()

    def acquire(self) -> None:
        """Create the lease, or take over one that is stale or of a dead writer on this host; refuse a
        live one. Each step is conditional: of writers racing, exactly one gets it."""
        for _ in range(3):  # a lease deleted or taken between our steps: look again
            try:
                self.tag = self.obj.create(self._body())
                break
            except _Taken:
                pass
            held = self.obj.read()
            if held is None:
                continue
            self._refuse_if_live(held[0])
            try:
                self.tag = self.obj.replace(self._body(), held[1])
                break
            except _Taken:
                continue
        else:
            raise StoreLockedError(f"{self.store} is being taken by another writer right now ({self.url}); "
                                   "wait for it to finish")
        self.last_ok = time.monotonic()
        self._thread.start()

    def _refuse_if_live(self, raw: bytes) -> None:
        try:
            held = json.loads(raw)
            age = time.time() - float(held["beat"])
            other_host = held["host"] != self.info["host"]
        except (ValueError, KeyError, TypeError):  # unreadable: taken over
            return
        if other_host and age < LEASE_STALE_S:  # this host's own lease: its writer is dead (we hold the flock)
            raise StoreLockedError(
                f"{self.store} is being written from host {held.get('host')} (pid {held.get('pid')}, `occdata "
                f"{held.get('command')}`, heartbeat {age:.0f} s ago); wait for it to finish, or delete {self.url} "
                f"if that writer is gone (a lease without heartbeat expires after {LEASE_STALE_S:.0f} s)")

    def _beat(self) -> None:
        while not self._stop.wait(LEASE_RENEW_S):
            try:
                self.tag = self.obj.replace(self._body(), self.tag)
                self.last_ok, self.last_error = time.monotonic(), ""
            except _Taken:
                self.lost = "another writer holds it now, or it was deleted"
                return
            except Exception as exc:  # noqa: BLE001 - an unreachable store: retried until the lease lapses
                self.last_error = f"{type(exc).__name__}: {exc}"
                if time.monotonic() - self.last_ok > _lapse_s():
                    self.lost = f"no heartbeat for {_lapse_s():.0f} s ({self.last_error})"
                    return

    def check(self) -> None:
        """Raise `LeaseLostError` once the lease is not this writer's any more."""
        if self.lost is None and self._thread.is_alive() and time.monotonic() - self.last_ok > _lapse_s():
            # the last renewal's error when one failed, else a renewal hanging in the network
            self.lost = f"no heartbeat for {_lapse_s():.0f} s" + (f" ({self.last_error})" if self.last_error else "")
        if self.lost is not None:
            raise LeaseLostError(
                f"lost the write lease {self.url} of {self.store} ({self.lost}); stopped writing. What was committed "
                "is kept; make sure no other writer is running, then rerun with --resume")

    def release(self) -> None:
        """Stop the heartbeat and delete the lease if it is still this writer's, never another's."""
        self._stop.set()
        self._thread.join(timeout=5)
        if self.lost is not None:
            return
        try:
            self.obj.delete(self.tag)
        except _Taken:
            self.lost = "another writer holds it now, or it was deleted"
        except Exception:  # noqa: BLE001, S110 - unreachable: the lease expires by itself after LEASE_STALE_S
            pass
