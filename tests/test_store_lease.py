"""Issue 48.6/48.7 and 47.4: the write lock and lease hold, and leave nothing behind.

- The local lock file is removed when a run ends (success, refusal, Ctrl-C); a live run stays
  protected, and a writer that opened the file just before its removal starts over.
- The S3 lease (moto on 127.0.0.1, the `s3` fixture of test_store_s3): stale by the store's own clock,
  never a host's; one identity per process (host, boot, pid namespace, pid, nonce); a store that
  ignores conditional writes is found at start; a task whose run lost its lease writes no chunk.
- A stopped build revokes its tasks' fence and waits for them before its last metadata write.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zarr
from test_store_s3 import _args, _cli, _free_port

import occdata.runtime.lock as lock_mod
from occdata.errors import OccDataError, OccDataWarning
from occdata.runtime.lock import Fence, LeaseLostError, StoreLockedError, lock_path, store_lock

REPO = Path(__file__).resolve().parents[1]
BUCKET = "occ-lease"  # moto keeps its buckets process-wide: not test_store_s3's


@pytest.fixture(scope="module")
def s3():
    """A local S3 server on 127.0.0.1 with this module's bucket; the environment points fsspec at it."""
    pytest.importorskip("s3fs")
    moto_server = pytest.importorskip("moto.server")
    import fsspec

    port = _free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "test",
           "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}
    mp = pytest.MonkeyPatch()
    for k, v in env.items():
        mp.setenv(k, v)
    fsspec.filesystem("s3").clear_instance_cache()
    fs = fsspec.filesystem("s3", skip_instance_cache=True)
    if not fs.exists(BUCKET):
        fs.mkdir(BUCKET)
    try:
        yield fs
    finally:
        mp.undo()
        server.stop()


# --- the local lock file ----------------------------------------------------------------------------
def test_lock_file_is_removed_after_success_refusal_and_ctrl_c(tmp_path: Path) -> None:
    out = tmp_path / "data.zarr"
    lock = lock_path(out)
    with store_lock(out, "build"):
        assert lock.is_file()
        with pytest.raises(StoreLockedError, match="being written by another process"):  # a live run: protected
            with store_lock(out, "build"):
                pass
        assert lock.is_file()  # the refused writer left the holder's file alone
    assert not lock.exists()
    with pytest.raises(OccDataError, match="refused"), store_lock(out, "build"):
        raise OccDataError("refused")
    assert not lock.exists()
    with pytest.raises(KeyboardInterrupt), store_lock(out, "build"):
        raise KeyboardInterrupt
    assert not lock.exists()
    assert list(tmp_path.iterdir()) == []


def test_a_writer_that_opened_the_removed_file_starts_over(tmp_path: Path, monkeypatch) -> None:
    """B opens the lock file while A holds it; A ends (removes it); B's lock on the removed file must
    not count: B locks the file the path names, and a third writer C is refused while B runs."""
    out = tmp_path / "data.zarr"
    path = lock_path(out)
    real_open = os.open
    opened: list[int] = []

    def open_then_a_ends(p, flags, mode=0o777):  # B's open lands on A's file, then A releases
        fd = real_open(p, flags, mode)
        if not opened:
            opened.append(fd)
            a_done.set()
            a.join(10)
        return fd

    a_in, a_done = threading.Event(), threading.Event()

    def writer_a() -> None:
        with store_lock(out, "labels"):
            a_in.set()
            a_done.wait(10)

    a = threading.Thread(target=writer_a)
    a.start()
    assert a_in.wait(10)
    monkeypatch.setattr(lock_mod.os, "open", open_then_a_ends)
    with store_lock(out, "build"):
        monkeypatch.setattr(lock_mod.os, "open", real_open)
        assert json.loads(path.read_text())["command"] == "build"  # B's record in the file the path names
        with pytest.raises(StoreLockedError, match="`occdata build`"):
            with store_lock(out, "verify"):
                pass
    assert not path.exists()


def test_refused_build_and_finished_labels_leave_no_lock(synth_root: Path, tmp_path: Path) -> None:
    """47.4: `occdata build --out afile.txt` (refused) left `afile.txt.lock`; `occdata labels` left
    `OUT.lock` beside its output."""
    afile = tmp_path / "afile.txt"
    afile.write_text("not a store")
    code, text = _cli("build", "--root", str(synth_root), "--gts", str(synth_root / "gts"), "--out", str(afile),
                      "--no-progress")
    assert code != 0, text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile.txt"]
    out = tmp_path / "labels"
    code, text = _cli("labels", "--root", str(synth_root), "--out", str(out), "--no-progress")
    assert code == 0, text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile.txt", "labels"]


# --- the lease on S3 --------------------------------------------------------------------------------
def _plant(fs, key: str, **fields) -> None:
    """A lease as another writer writes it (its own clock in `beat`)."""
    body = {"host": "elsewhere", "pid": 1, "boot": "b", "pidns": "pid:[1]", "command": "build",
            "beat": time.time(), "nonce": "theirs", **fields}
    fs.pipe(key, json.dumps(body).encode())


def _holder(fs, key: str) -> dict:
    return json.loads(fs.cat(key))


def test_a_clock_70_s_ahead_cannot_take_a_live_lease(s3, monkeypatch) -> None:
    """Was: age = this host's time.time() - the holder's beat. The holder renewed 21 s ago by its clock
    (just written, by the store's); a taker whose clock runs 70 s ahead saw 91 s > 90 and took it."""
    real = time.time
    monkeypatch.setattr(lock_mod, "time", SimpleNamespace(time=lambda: real() + 70, monotonic=time.monotonic))
    url, key = f"s3://{BUCKET}/skew.zarr", f"{BUCKET}/skew.zarr.lock"
    _plant(s3, key, beat=real() - 21)
    with pytest.raises(StoreLockedError, match=r"from host elsewhere .*renewed \d s ago by the store's clock"):
        with store_lock(url, "build"):
            pass
    assert _holder(s3, key)["nonce"] == "theirs"
    s3.rm(key)


def test_a_lease_stale_by_the_store_clock_is_taken_whatever_its_beat_says(s3, monkeypatch) -> None:
    """A holder whose clock runs an hour ahead wrote a beat in the future: by its own numbers never stale.
    The store's LastModified decides: unrenewed for LEASE_STALE_S, it is taken over."""
    monkeypatch.setattr(lock_mod, "LEASE_STALE_S", 2.0)
    url, key = f"s3://{BUCKET}/stale.zarr", f"{BUCKET}/stale.zarr.lock"
    _plant(s3, key, beat=time.time() + 3600)
    time.sleep(3.2)  # LastModified and Date have one-second resolution
    with store_lock(url, "build"):
        assert _holder(s3, key)["host"] == socket.gethostname()
    assert not s3.exists(key)


def test_two_processes_of_one_host_name_keep_apart(s3) -> None:
    """Was: a lease of this host name whose local lock was free counted as this host's dead writer and
    was taken over: two containers sharing a host name took each other's lease. Now only a writer of
    this machine and pid namespace whose pid is gone is taken over."""
    me = {"host": socket.gethostname(), "boot": Path("/proc/sys/kernel/random/boot_id").read_text().strip(),
          "pidns": os.readlink("/proc/self/ns/pid")}
    url, key = f"s3://{BUCKET}/twins.zarr", f"{BUCKET}/twins.zarr.lock"
    # another container: same host name, its own pid namespace (its pid may even be ours)
    _plant(s3, key, host=me["host"], pid=os.getpid(), boot=me["boot"], pidns="pid:[4026531836]x")
    with pytest.raises(StoreLockedError, match=f"from host {me['host']}"):
        with store_lock(url, "build"):
            pass
    # this machine, this namespace, a live process (ours): refused too
    _plant(s3, key, host=me["host"], pid=os.getpid(), boot=me["boot"], pidns=me["pidns"])
    with pytest.raises(StoreLockedError):
        with store_lock(url, "build"):
            pass
    # this machine, this namespace, a pid that has exited (a writer killed with -9): taken over
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    _plant(s3, key, host=me["host"], pid=gone.pid, boot=me["boot"], pidns=me["pidns"])
    with store_lock(url, "build"):
        assert _holder(s3, key)["pid"] == os.getpid()
    assert not s3.exists(key)


def test_a_store_ignoring_conditional_writes_is_found_at_start(s3, monkeypatch) -> None:
    """A store (or a botocore too old: s3fs drops arguments it does not know) that ignores If-Match and
    If-None-Match: one warning line at start, and a live lease is still refused (checked first)."""
    real_call = lock_mod._S3Object._call

    def ignoring(self, op, **kw):
        kw.pop("IfMatch", None)
        kw.pop("IfNoneMatch", None)
        return real_call(self, op, **kw)

    monkeypatch.setattr(lock_mod._S3Object, "_call", ignoring)
    url, key = f"s3://{BUCKET}/plainish.zarr", f"{BUCKET}/plainish.zarr.lock"
    with pytest.warns(OccDataWarning, match="ignores conditional writes") as caught:
        with store_lock(url, "build"):
            assert _holder(s3, key)["pid"] == os.getpid()
    assert len(caught) == 1 and "\n" not in str(caught[0].message)
    assert not s3.exists(key)
    assert not [p for p in s3.ls(BUCKET) if "probe" in p]  # the probe object is removed
    _plant(s3, key)
    with pytest.warns(OccDataWarning), pytest.raises(StoreLockedError, match="from host elsewhere"):
        with store_lock(url, "build"):
            pass
    s3.rm(key)


def test_release_waits_for_a_renewal_in_flight(s3, monkeypatch) -> None:
    """The body ends while a renewal is on the wire: the release joins the heartbeat and deletes with
    the tag that renewal wrote (was: a 5 s wait, then a delete with a tag the thread might change)."""
    monkeypatch.setattr(lock_mod, "LEASE_RENEW_S", 0.05)
    real_replace = lock_mod._S3Object.replace
    in_flight = threading.Event()

    def slow(self, data, tag):
        in_flight.set()
        time.sleep(0.5)
        return real_replace(self, data, tag)

    monkeypatch.setattr(lock_mod._S3Object, "replace", slow)
    url, key = f"s3://{BUCKET}/join.zarr", f"{BUCKET}/join.zarr.lock"
    with store_lock(url, "build"):
        assert in_flight.wait(10)
    assert not s3.exists(key)


def test_a_fence_fails_once_another_writer_holds_the_lease(s3) -> None:
    url, key = f"s3://{BUCKET}/fence.zarr", f"{BUCKET}/fence.zarr.lock"
    with pytest.raises(LeaseLostError), store_lock(url, "build") as lock:
        lock.fence.check()
        _plant(s3, key)
        with pytest.raises(LeaseLostError, match="another writer holds it now"):
            lock.fence.check()
    s3.rm(key)


def test_a_task_whose_lease_was_taken_mid_task_writes_no_chunk(s3, synth_root: Path, monkeypatch) -> None:
    """Was: on a lost lease, a task already converting went on writing its chunks. Another host takes
    the lease while block 1 converts: from then on, no object of the store is written or rewritten."""
    import occdata.store.blocks as blocks

    monkeypatch.setattr(lock_mod, "LEASE_RENEW_S", 60.0)  # the task, not the heartbeat, must notice
    url, key = f"s3://{BUCKET}/midtask.zarr", f"{BUCKET}/midtask.zarr.lock"
    real_convert = blocks.convert_block
    seen: dict[str, str] = {}

    def taken_during_block_1(job):
        if job.block == 1:
            seen.update(_etags(s3, f"{BUCKET}/midtask.zarr"))
            _plant(s3, key)
        return real_convert(job)

    monkeypatch.setattr(blocks, "convert_block", taken_during_block_1)
    code, text = _cli(*_args(synth_root, url))
    assert code == 1 and "lost the write lease" in text, text
    assert seen and _etags(s3, f"{BUCKET}/midtask.zarr") == seen  # nothing new, nothing rewritten
    state = zarr.open_group(url, mode="r")["status/state"][:]
    assert (state[:2] == 1).all() and (state[2:] == 0).all(), state
    assert _holder(s3, key)["nonce"] == "theirs"
    s3.rm(key)


def _etags(fs, prefix: str) -> dict[str, str]:
    fs.invalidate_cache()
    return {p: info["ETag"] for p, info in fs.find(prefix, detail=True).items() if p.startswith(prefix + "/")}


def test_a_fence_of_a_local_run_fails_after_revoke_and_after_the_run(tmp_path: Path) -> None:
    out = tmp_path / "data.zarr"
    with store_lock(out, "build") as lock:
        fence = lock.fence
        fence.check()
        lock.revoke()
        with pytest.raises(LeaseLostError):
            fence.check()
        with pytest.raises(StoreLockedError):  # revoked, still protected
            with store_lock(out, "build"):
                pass
    with store_lock(out, "build"):  # a later run: another nonce
        with pytest.raises(LeaseLostError):
            fence.check()
    with pytest.raises(LeaseLostError):
        Fence(str(lock_path(out)), str(out), fence.nonce).check()


# --- 48.7: no metadata write while a task may still run ----------------------------------------------
@pytest.mark.timeout(240)
def test_ctrl_c_waits_for_running_tasks_and_fences_them(synth_root: Path, tmp_path: Path, monkeypatch) -> None:
    """Ctrl-C while a worker's task is still converting block 0. Was: the cancel returned at once, the
    build wrote its metadata and returned, and the task went on to write its block (done flags).
    Now the cancel revokes the fence and waits: the task stops at its first write, before the build
    returns; nothing of block 0 is written."""
    from distributed import Client, LocalCluster

    import occdata.store.blocks as blocks
    import occdata.store.build as build
    from occdata.runtime.cluster import ClusterConfig, Interrupted
    from occdata.store.build import BuildConfig, build_store

    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # the worker's setup sets them
        monkeypatch.setenv(name, os.environ.get(name, ""))
    real_convert = blocks.convert_block
    started, finished = threading.Event(), threading.Event()

    def slow_block_0(job):
        if job.block != 0:
            return real_convert(job)
        started.set()
        try:
            time.sleep(2.0)  # still converting when Ctrl-C comes
            return real_convert(job)
        finally:
            finished.set()

    wrote_while_running: list[bool] = []
    real_consolidate = build.consolidate

    def consolidate(out):
        wrote_while_running.append(started.is_set() and not finished.is_set())
        return real_consolidate(out)

    monkeypatch.setattr(blocks, "convert_block", slow_block_0)
    monkeypatch.setattr(build, "consolidate", consolidate)
    out = tmp_path / "s.zarr"
    cfg = BuildConfig(root=synth_root, out=out, gts=synth_root / "gts", block_samples=2, progress=False,
                      cluster=ClusterConfig(workers=1), on_error="skip")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster, \
            Client(cluster, set_as_default=False) as client:
        def ctrl_c() -> None:
            started.wait(60)
            os.kill(os.getpid(), signal.SIGINT)

        threading.Thread(target=ctrl_c, daemon=True).start()
        with pytest.raises(Interrupted):
            build_store(cfg, client=client)
        assert finished.is_set()  # the build returned only once the task had ended
    assert not any(wrote_while_running), wrote_while_running
    state = zarr.open_group(str(out), mode="r")["status/state"][:]
    assert (state[:2] == 0).all(), state  # the task's writes were fenced: block 0 stays pending
    assert np.count_nonzero(state) == 0, state
