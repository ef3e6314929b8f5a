"""One writer per store: an advisory `fcntl` lock on `<store>.lock`, next to the store.

The lock file sits beside the store (not inside it) because a new store only appears, by an atomic
rename, once its layout is complete. The writer removes it when it ends (success, error, Ctrl-C),
while still holding the lock; a writer that opened the old file meanwhile sees, once it holds the
lock, that the path no longer names the file it locked, and starts over on the new one. So deleting
cannot let two writers in, and no `.lock` stays behind but after a kill -9, where the kernel drops
the lock and the next writer takes the file over. Its content (identity, start time, command)
serves the message of a writer that is refused, and the run's fence (`Fence`).

An object store (s3://...) has no advisory lock. There the lock is twofold: the same `fcntl` lock on
a local file named after the URL (two writers on one host), and a lease object `<store>.lock`
holding the holder's identity (host, pid, boot id, pid namespace and a random nonce) renewed every
`LEASE_RENEW_S`. A lease is stale once the store's own clock says it was last written
`LEASE_STALE_S` ago (its LastModified against the server's Date header): no host's clock counts.
A live lease is taken over only when its writer is provably dead: same host, same boot, same pid
namespace, and its pid gone. Two containers that share a host name differ in one of those.

On S3 every write of the lease is conditional, so one host holds it: it is created with
`If-None-Match: *` (of two writers racing, one gets 412), taken over and renewed with `If-Match:
<the ETag last seen>`, and deleted with `If-Match: <our ETag>` (never another holder's lease). A
store that ignores those headers (or a botocore too old to send them: s3fs drops the arguments it
does not know) is found at start by a probe whose second create must fail; it gets one warning and
the checked-then-written lease of other stores. A renewal that finds the lease changed, or none that
succeeded for `LEASE_STALE_S - LEASE_RENEW_S` (others may take it over soon), loses the lease:
`StoreLock.check()` then raises `LeaseLostError`, which the writer polls and `store_lock` raises at the
end. The release stops and joins the heartbeat first, so it deletes with the tag last written.

Tasks running elsewhere (Dask workers) cannot poll the writer: they hold its `Fence` (the lock
file's or the lease's nonce) and check it before each chunk they write. A run that ends, is
cancelled or loses its lease changes or removes that record, and another writer's lease carries
another nonce, so a task left running writes nothing more.
"""

from __future__ import annotations

import datetime
import email.utils
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
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from occdata.errors import OccDataError, OccDataWarning

__all__ = ["LEASE_RENEW_S", "LEASE_STALE_S", "Fence", "LeaseLostError", "StoreLock", "StoreLockedError",
           "lock_path", "store_lock"]

LEASE_RENEW_S = 20.0
LEASE_STALE_S = 90.0
_JOIN_S = 10.0  # the heartbeat's last renewal, at most: past it the lease is left to expire, never raced
_RETRIES = 5  # a lock file removed or a lease changed between our steps: look again


class StoreLockedError(OccDataError):
    """Another process is writing the store."""


class LeaseLostError(OccDataError):
    """The lease of a remote store lapsed, or another writer holds it now: this writer must stop."""


def _lost(where: str, store: str, why: str) -> LeaseLostError:
    return LeaseLostError(f"lost the write lease {where} of {store} ({why}); stopped writing. What was committed "
                          "is kept; make sure no other writer is running, then rerun with --resume")


@dataclass(frozen=True)
class Fence:
    """A run's token for its tasks (picklable, small): `check()` raises `LeaseLostError` unless the lock
    record at `where` (the lock file's path, or the lease object's URL) still carries `nonce`."""

    where: str
    store: str
    nonce: str

    def check(self) -> None:
        try:
            nonce = _read_nonce(self.where)
        except OSError as exc:  # unreadable: writing on could overwrite another writer's chunks
            raise _lost(self.where, self.store, f"cannot read it: {type(exc).__name__}: {exc}") from None
        if nonce != self.nonce:
            raise _lost(self.where, self.store, "the run that held it ended or was stopped, or another writer "
                        "holds it now")


def _read_nonce(where: str) -> str | None:
    """The nonce of the lock record at `where`; None when there is none (removed, or being rewritten)."""
    try:
        if "://" in where:
            import fsspec

            fs, path = fsspec.core.url_to_fs(where)
            raw = bytes(fs.cat_file(path))
        else:
            raw = Path(where).read_bytes()
        return str(json.loads(raw)["nonce"])
    except (FileNotFoundError, ValueError, KeyError, TypeError):
        return None


class StoreLock:
    """What `store_lock` yields. `check()` raises `LeaseLostError` once a remote store's lease is no
    longer this writer's (a no-op for a local store, whose lock the kernel holds). `fence` is what
    the run's tasks check before each write; `revoke()` makes every such fence fail while this
    writer still holds the store (a run stopping before its last metadata write)."""

    def __init__(self, fence: Fence, revoke: Callable[[], None], lease: _Lease | None = None) -> None:
        self.fence, self._revoke, self._lease = fence, revoke, lease

    def check(self) -> None:
        if self._lease is not None:
            self._lease.check()

    def revoke(self) -> None:
        self._revoke()


def lock_path(store: str | Path) -> Path:
    """The local lock file: beside a local store; for a URL, a file named after it in the temp folder."""
    if "://" in str(store):
        digest = hashlib.sha256(str(store).rstrip("/").encode()).hexdigest()[:24]
        return Path(tempfile.gettempdir()) / "occdata-locks" / f"{digest}.lock"
    p = Path(store)
    return p.with_name(p.name + ".lock")


def _read_line(path: str) -> str:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return ""


def _identity() -> dict[str, Any]:
    """This process among all writers: host, pid, the kernel's boot id and pid namespace (two
    containers sharing a host name differ in one), and a random nonce (two runs of one pid differ)."""
    try:
        pidns = os.readlink("/proc/self/ns/pid")
    except OSError:
        pidns = ""
    return {"host": socket.gethostname(), "pid": os.getpid(), "boot": _read_line("/proc/sys/kernel/random/boot_id"),
            "pidns": pidns, "nonce": uuid.uuid4().hex}


def _provably_dead(held: dict[str, Any], me: dict[str, Any]) -> bool:
    """True only when `held` names a process of this very machine and pid namespace that is gone."""
    if not all(me[k] and held.get(k) == me[k] for k in ("host", "boot", "pidns")):
        return False
    pid = held.get("pid")
    if not isinstance(pid, int) or pid <= 0 or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # exists, another user's
        return False
    return False


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _lock_file(path: Path, store: str | Path) -> int:
    """Open and lock `path`: its descriptor, once it is the file the path names (see the module docstring)."""
    for _ in range(_RETRIES):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)  # the umask applies
        except OSError as exc:
            raise OccDataError(f"cannot create the lock file {path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise StoreLockedError(f"{store} is being written by another process ({_holder(path)}); wait for it "
                                   f"to finish or stop it (lock file {path})") from None
        if _same_file(fd, path):
            return fd
        os.close(fd)  # its holder removed it after we opened it: lock the one the path names now
    raise StoreLockedError(f"{store} is being taken by another writer right now (lock file {path}); wait for it "
                           "to finish")


def _write_record(fd: int, info: dict[str, Any]) -> None:
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)


@contextmanager
def store_lock(store: str | Path, command: str) -> Iterator[StoreLock]:
    """Hold the store's write lock for the `with` body; refuse at once if another writer holds it.
    The lock file is removed when the body ends, however it ends.

    A URL store also takes the lease object `<store>.lock` (see the module docstring); a lease lost
    during the body raises `LeaseLostError` from `StoreLock.check()` and, when the body ends, here.
    """
    path = lock_path(store)
    fd = _lock_file(path, store)
    try:
        info = {**_identity(), "command": command,
                "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
        _write_record(fd, info)
        if "://" in str(store):
            lease = _Lease(str(store).rstrip("/") + ".lock", info)
            lease.acquire()
            try:
                yield StoreLock(Fence(lease.url, lease.store, info["nonce"]), lease.revoke, lease)
            finally:
                lease.release()
            lease.check()  # reached when the body ended by itself: a lease lost meanwhile fails the run
        else:
            def revoke() -> None:
                _write_record(fd, {**info, "nonce": uuid.uuid4().hex})

            # absolute: a task's worker may run in another folder (a --scheduler worker)
            yield StoreLock(Fence(os.path.abspath(path), str(store), info["nonce"]), revoke)
    finally:
        with suppress(OSError):
            if _same_file(fd, path):
                path.unlink()  # still locked: a writer waiting on this file starts over (`_lock_file`)
        os.close(fd)  # releases the flock


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text() or "{}")
        return f"`occdata {info['command']}`, pid {info['pid']} on host {info['host']}, started {info['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"


class _Taken(Exception):
    """A conditional write or delete found the lease object changed or gone since this writer saw it."""


@dataclass(frozen=True)
class _Held:
    """The lease object as read: its bytes, tag, and age in seconds by the store's clock."""

    raw: bytes
    tag: str
    age_s: float


def _age_s(modified: datetime.datetime, server_now: str | None) -> float:
    """`server_now` (an HTTP Date header) minus `modified`; this host's clock only when there is no Date."""
    now = email.utils.parsedate_to_datetime(server_now) if server_now else datetime.datetime.now(datetime.UTC)
    if modified.tzinfo is None:
        modified = modified.replace(tzinfo=datetime.UTC)
    return (now - modified).total_seconds()


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

    def read(self) -> _Held | None:
        try:  # the ETag first: the content read next is the same or newer, so a replace on it is safe
            head = self._call("head_object")
            raw = bytes(self.fs.cat_file(self.path))
        except (_Taken, FileNotFoundError):
            return None
        date = head.get("ResponseMetadata", {}).get("HTTPHeaders", {}).get("date")
        return _Held(raw, str(head["ETag"]), _age_s(head["LastModified"], date))

    def delete(self, tag: str) -> None:
        self._call("delete_object", IfMatch=tag)

    def honours_conditions(self) -> bool:
        """A probe object: a second create, a replace and a delete on a wrong tag must all fail."""
        probe = _S3Object(self.fs, f"{self.path}.probe-{uuid.uuid4().hex}")
        wrong = '"' + "0" * 32 + '"'
        probe._call("put_object", Body=b"", IfNoneMatch="*")
        try:
            for op, kw in (("put_object", {"Body": b"", "IfNoneMatch": "*"}),
                           ("put_object", {"Body": b"", "IfMatch": wrong}), ("delete_object", {"IfMatch": wrong})):
                try:
                    probe._call(op, **kw)
                    return False
                except _Taken:
                    pass
            return True
        finally:
            with suppress(Exception):
                self.fs.call_s3("delete_object", Bucket=probe.bucket, Key=probe.key)


class _PlainObject:
    """The lease object on a store without a conditional request known here: created checked, then
    written (`pipe_file(mode="create")`, exclusive where the filesystem implements it); a replace or
    delete compares the content first, so two writers acting at the same instant can both succeed.
    Its age is the file's modification time against this host's clock."""

    exclusive = False

    def __init__(self, fs: Any, path: str) -> None:
        self.fs, self.path = fs, path

    def create(self, data: bytes) -> str:
        if self.read() is not None:
            raise _Taken("exists")
        try:
            self.fs.pipe_file(self.path, data, mode="create")
        except FileExistsError:
            raise _Taken("exists") from None
        return hashlib.sha256(data).hexdigest()

    def read(self) -> _Held | None:
        try:
            data = bytes(self.fs.cat_file(self.path))
            modified = self.fs.modified(self.path)
        except FileNotFoundError:
            return None
        except (NotImplementedError, AttributeError):  # no modification time: the holder's own beat
            try:
                age = time.time() - float(json.loads(data)["beat"])
            except (ValueError, KeyError, TypeError):
                age = LEASE_STALE_S
            return _Held(data, hashlib.sha256(data).hexdigest(), age)
        return _Held(data, hashlib.sha256(data).hexdigest(), _age_s(modified, None))

    def _expect(self, tag: str) -> None:
        held = self.read()
        if held is None or held.tag != tag:
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
        obj = _S3Object(fs, path)
        if obj.honours_conditions():
            return obj
        why = ("ignores conditional writes (a second PUT with If-None-Match: * succeeded; they need botocore "
               ">= 1.35.69 and a store that implements them)")
    else:
        why = f"{protocols[0]}:// has no conditional write known to occdata"
    warnings.warn(OccDataWarning(f"{url}: {why}, so its write lease is checked, then written: two writers "
                                 "starting at the same moment could both take it"), stacklevel=4)
    return _PlainObject(fs, path)


def _lapse_s() -> float:
    """Without a renewal for this long the lease counts as lost: others take it over at LEASE_STALE_S."""
    return LEASE_STALE_S - LEASE_RENEW_S


class _Lease:
    """This writer's hold on the lease object `url` (the local lock is already held)."""

    def __init__(self, url: str, info: dict[str, Any]) -> None:
        self.url, self.store = url, url[: -len(".lock")]
        self.info = dict(info)
        self.obj = _lease_object(url)
        self.tag = ""
        self.last_ok = time.monotonic()
        self.last_error = ""  # the latest failed renewal's "Type: message" ("" while renewals succeed)
        self.lost: str | None = None
        self._io = threading.Lock()  # one write of the lease at a time: a renewal, a revoke
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="occdata-lease", daemon=True)

    def _body(self) -> bytes:
        return json.dumps({**self.info, "beat": time.time()}).encode()  # beat: for people; never compared

    def acquire(self) -> None:
        """Create the lease, or take over one that is stale by the store's clock or whose writer is
        provably dead; refuse a live one. Each step is conditional: of writers racing, one gets it."""
        for _ in range(_RETRIES):
            try:
                self.tag = self.obj.create(self._body())
                break
            except _Taken:
                pass
            held = self.obj.read()
            if held is None:
                continue
            self._refuse_if_live(held)
            try:
                self.tag = self.obj.replace(self._body(), held.tag)
                break
            except _Taken:
                continue
        else:
            raise StoreLockedError(f"{self.store} is being taken by another writer right now ({self.url}); "
                                   "wait for it to finish")
        self.last_ok = time.monotonic()
        self._thread.start()

    def _refuse_if_live(self, held: _Held) -> None:
        if held.age_s >= LEASE_STALE_S:
            return
        try:
            info = json.loads(held.raw)
            if not isinstance(info, dict):
                raise TypeError
        except (ValueError, TypeError):
            info = {}
        if _provably_dead(info, self.info):
            return
        raise StoreLockedError(
            f"{self.store} is being written from host {info.get('host', '?')} (pid {info.get('pid', '?')}, "
            f"`occdata {info.get('command', '?')}`, lease renewed {max(held.age_s, 0.0):.0f} s ago by the store's "
            f"clock); wait for it to finish, or delete {self.url} if that writer is gone (a lease without "
            f"heartbeat expires after {LEASE_STALE_S:.0f} s)")

    def _renew(self) -> None:
        with self._io:
            self.tag = self.obj.replace(self._body(), self.tag)

    def _beat(self) -> None:
        while not self._stop.wait(LEASE_RENEW_S):
            try:
                self._renew()
                self.last_ok, self.last_error = time.monotonic(), ""
            except _Taken:
                self.lost = "another writer holds it now, or it was deleted"
                return
            except Exception as exc:  # noqa: BLE001 - an unreachable store: retried until the lease lapses
                self.last_error = f"{type(exc).__name__}: {exc}"
                if time.monotonic() - self.last_ok > _lapse_s():
                    self.lost = f"no heartbeat for {_lapse_s():.0f} s ({self.last_error})"
                    return

    def revoke(self) -> None:
        """A new nonce in the lease: every task's `Fence` fails from now on; this writer keeps the lease."""
        self.info["nonce"] = uuid.uuid4().hex
        with suppress(Exception):  # a lost or unreachable lease fences the tasks by itself
            self._renew()

    def check(self) -> None:
        """Raise `LeaseLostError` once the lease is not this writer's any more."""
        if self.lost is None and self._thread.is_alive() and time.monotonic() - self.last_ok > _lapse_s():
            # the last renewal's error when one failed, else a renewal hanging in the network
            self.lost = f"no heartbeat for {_lapse_s():.0f} s" + (f" ({self.last_error})" if self.last_error else "")
        if self.lost is not None:
            raise _lost(self.url, self.store, self.lost)

    def release(self) -> None:
        """Stop and join the heartbeat, then delete the lease with the tag it last wrote, if the lease
        is still this writer's. A heartbeat still in the network after `_JOIN_S`: the lease is left to
        expire (its tag may be changing), never deleted by a guess."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=_JOIN_S)
        if self.lost is not None or self._thread.is_alive():
            return
        try:
            self.obj.delete(self.tag)
        except _Taken:
            self.lost = "another writer holds it now, or it was deleted"
        except Exception:  # noqa: BLE001, S110 - unreachable: the lease expires by itself after LEASE_STALE_S
            pass
