"""Issue 24: `occdata build --out s3://bucket/data.zarr` against a local S3 server (moto, 127.0.0.1).

The server runs in this process for the module; fsspec/botocore find it through `AWS_ENDPOINT_URL`
(inherited by the Dask workers and the CLI subprocesses). The store must hold the same arrays,
byte for byte, as a local build, pass verify, resume, and keep its one-writer rule.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from gates import gated_tree
from proc_tools import alive, descendants, wait_for
from test_store_build import store_digest

from cli.occdata_cli import main
from occdata.runtime.lock import LeaseLostError, StoreLockedError, store_lock
from occdata.store.build import BuildConfig, build_store

pytest.importorskip("s3fs")
moto_server = pytest.importorskip("moto.server")

REPO = Path(__file__).resolve().parents[1]
BUCKET = "occ-test"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """A fresh S3 server on 127.0.0.1 with one bucket; the environment points fsspec at it."""
    port = _free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "test",
           "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    import fsspec

    fsspec.filesystem("s3").clear_instance_cache()
    fs = fsspec.filesystem("s3", skip_instance_cache=True)
    fs.mkdir(BUCKET)
    try:
        yield fs
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        server.stop()


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


def _args(root: Path, out: str, *extra: str) -> list[str]:
    return ["build", "--root", str(root), "--gts", str(root / "gts"), "--out", out, "--block-samples", "2",
            "--no-progress", *extra]


@pytest.fixture(scope="module")
def local_digest(synth_root: Path, tmp_path_factory) -> dict[str, str]:
    out = tmp_path_factory.mktemp("s3ref") / "ref.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=synth_root / "gts", block_samples=2, progress=False))
    return store_digest(out)


def test_s3_build_same_bytes_verify_resume(s3, synth_root: Path, local_digest) -> None:
    url = f"s3://{BUCKET}/two.zarr"
    code, text = _cli(*_args(synth_root, url, "--workers", "2"))
    assert code == 0, text
    assert store_digest(url) == local_digest  # type: ignore[arg-type]
    assert not s3.exists(f"{BUCKET}/two.zarr.staging") and not s3.exists(f"{BUCKET}/two.zarr.lock")
    code, text = _cli("verify", "--store", url, "--no-progress")
    assert code == 0, text
    code, text = _cli(*_args(synth_root, url))
    assert code != 0 and "store exists" in text
    code, text = _cli(*_args(synth_root, url, "--resume"))
    assert code == 0 and "0 processed" in text, text


def test_s3_verify_finds_a_missing_chunk(s3, synth_root: Path) -> None:
    url = f"s3://{BUCKET}/miss.zarr"
    code, text = _cli(*_args(synth_root, url))
    assert code == 0, text
    s3.rm(f"{BUCKET}/miss.zarr/calib/K/c/1/0/0/0")
    code, text = _cli("verify", "--store", url, "--no-progress")
    assert code == 1 and "calib/K" in text, text


def test_s3_second_writer_is_refused(s3, synth_root: Path) -> None:
    url = f"s3://{BUCKET}/locked.zarr"
    with store_lock(url, "build"):
        assert s3.exists(f"{BUCKET}/locked.zarr.lock")
        code, text = _cli(*_args(synth_root, url))
        assert code != 0 and "being written by another process" in text, text
    assert not s3.exists(f"{BUCKET}/locked.zarr.lock")


def test_s3_lease_of_another_host_refuses(s3, synth_root: Path) -> None:
    import json

    url = f"s3://{BUCKET}/lease.zarr"
    s3.pipe(f"{BUCKET}/lease.zarr.lock", json.dumps({"host": "elsewhere", "pid": 1, "command": "build",
                                                      "beat": time.time()}).encode())
    with pytest.raises(StoreLockedError, match="from host elsewhere"):
        with store_lock(url, "build"):
            pass
    s3.rm(f"{BUCKET}/lease.zarr.lock")


# --- one host holds the lease (issue 40, item 5) -----------------------------------------------------
def _plant_lease(s3, key: str, host: str = "elsewhere") -> None:
    """Another host's fresh lease, written as that host would (its writer took over ours)."""
    import json

    s3.pipe(key, json.dumps({"host": host, "pid": 1, "command": "build", "beat": time.time(),
                             "nonce": "theirs"}).encode())


def _holder(s3, key: str) -> str:
    import json

    return json.loads(s3.cat(key))["host"]


def test_s3_writers_of_eight_hosts_racing_exactly_one_wins(s3, tmp_path: Path, monkeypatch) -> None:
    """Was: read, then write: writers that read before any wrote all took the lease. Eight threads,
    each standing for a host (its own host name and local lock file), start together: one holds the
    lease, the seven others are refused naming it, and the lease names the winner until it ends."""
    from types import SimpleNamespace

    import occdata.runtime.lock as lock_mod

    local = threading.local()
    monkeypatch.setattr(lock_mod, "socket", SimpleNamespace(gethostname=lambda: local.host))
    monkeypatch.setattr(lock_mod, "lock_path", lambda store: tmp_path / f"{local.host}.lock")
    url, key, n = f"s3://{BUCKET}/race.zarr", f"{BUCKET}/race.zarr.lock", 8
    start, done = threading.Barrier(n), threading.Event()
    won: list[str] = []
    refused: list[str] = []

    def writer(i: int) -> None:
        local.host = f"host{i}"
        start.wait()
        try:
            with store_lock(url, "build"):
                won.append(local.host)
                done.wait(30)
        except StoreLockedError as exc:
            refused.append(str(exc))

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    assert wait_for(lambda: len(won) + len(refused) == n, 30), (won, refused)
    try:
        assert len(won) == 1, won
        assert _holder(s3, key) == won[0]
        assert all(f"from host {won[0]}" in r or "being taken by another writer" in r for r in refused), refused
    finally:
        done.set()
        for t in threads:
            t.join(30)
    assert not s3.exists(key)


def test_s3_a_build_whose_lease_was_taken_stops(s3, synth_root: Path, monkeypatch) -> None:
    """Was: the heartbeat overwrote whatever lease it found and swallowed its errors, so a writer whose
    lease another host had taken kept writing. Here another host takes the lease while block 1 of 3
    converts: the build stops before block 2 with one line, and leaves the other host's lease alone."""
    import zarr

    import occdata.runtime.lock as lock_mod
    import occdata.store.blocks as blocks

    monkeypatch.setattr(lock_mod, "LEASE_RENEW_S", 0.1)
    url, key = f"s3://{BUCKET}/taken.zarr", f"{BUCKET}/taken.zarr.lock"
    real_convert = blocks.convert_block

    def taken_during_block_1(job):
        if job.block == 1:
            _plant_lease(s3, key)
            time.sleep(1.0)  # ten heartbeats: the first one finds the lease changed
        return real_convert(job)

    monkeypatch.setattr(blocks, "convert_block", taken_during_block_1)
    code, text = _cli(*_args(synth_root, url))
    assert code == 1, text
    lines = [ln for ln in text.splitlines() if ln.startswith("Error:")]  # (before it: the labels line)
    assert len(lines) == 1 and lines[0].startswith(f"Error: lost the write lease s3://{key}"), text
    assert "another writer holds it now" in text and "Traceback" not in text
    state = zarr.open_group(url, mode="r")["status/state"][:]
    assert (state[:2] == 1).all() and (state[4:] == 0).all(), state  # block 2 never started
    assert _holder(s3, key) == "elsewhere"
    s3.rm(key)


def test_s3_a_heartbeat_that_keeps_failing_stops_the_writer(s3, monkeypatch) -> None:
    """A store that stops answering renewals: once no renewal succeeded for LEASE_STALE_S -
    LEASE_RENEW_S (others may take the lease over soon), `check()` raises; was: errors swallowed."""
    import occdata.runtime.lock as lock_mod

    def unreachable(self, data, tag):
        raise ConnectionRefusedError(111, "Connection refused")

    # A stale time 40 renewals long: on a loaded machine the heartbeat thread may first run late, and the
    # lease must lapse after renewals have failed (and named their cause), not before the first one ran.
    monkeypatch.setattr(lock_mod, "LEASE_RENEW_S", 0.05)
    monkeypatch.setattr(lock_mod, "LEASE_STALE_S", 2.0)
    monkeypatch.setattr(lock_mod._S3Object, "replace", unreachable)
    url = f"s3://{BUCKET}/lapse.zarr"
    t0 = time.monotonic()
    with pytest.raises(LeaseLostError, match=r"no heartbeat for \d+ s \(ConnectionRefusedError"):
        with store_lock(url, "build") as lock:
            while time.monotonic() - t0 < 10:
                lock.check()
                time.sleep(0.02)
    assert time.monotonic() - t0 < 8
    s3.rm(f"{BUCKET}/lapse.zarr.lock")  # left in place: this writer cannot tell whose it is now


def test_s3_release_leaves_another_holders_lease(s3) -> None:
    """Was: the final delete removed the lease whoever held it. A lease taken over by another host
    while this writer still ran (before a heartbeat noticed): the release keeps it, and the writer
    is told, since its last writes raced with the other one's."""
    url, key = f"s3://{BUCKET}/keep.zarr", f"{BUCKET}/keep.zarr.lock"
    with pytest.raises(LeaseLostError, match="another writer holds it now"):
        with store_lock(url, "build"):
            _plant_lease(s3, key)
    assert _holder(s3, key) == "elsewhere"
    s3.rm(key)


def test_lease_without_conditional_writes_warns_and_still_refuses_a_second_host(tmp_path: Path) -> None:
    """memory:// stands for an fsspec store without conditional requests: one warning line says the
    lease is checked, then written; a live lease of another host is still refused, and the holder
    deletes only its own lease."""
    import fsspec

    from occdata.errors import OccDataWarning

    fs = fsspec.filesystem("memory")
    url = "memory://leases/plain.zarr"
    with pytest.warns(OccDataWarning, match="no conditional write known to occdata"):
        with store_lock(url, "build"):
            assert fs.exists("/leases/plain.zarr.lock")
    assert not fs.exists("/leases/plain.zarr.lock")
    _plant_lease(fs, "/leases/plain.zarr.lock")
    with pytest.warns(OccDataWarning), pytest.raises(StoreLockedError, match="from host elsewhere"):
        with store_lock(url, "build"):
            pass
    assert _holder(fs, "/leases/plain.zarr.lock") == "elsewhere"
    fs.rm("/leases/plain.zarr.lock")


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_s3_client_kill9_then_resume(s3, real_nuscenes_root, real_occ3d_label, tmp_path) -> None:
    """kill -9 of the client mid-build on S3: no process left, the lease of the dead writer on this
    host is taken over, --resume gives the same bytes as an uninterrupted local build."""
    from replicated_tree import make_replicated_tree

    tree = make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path / "ns", 2, 8)
    ref = tmp_path / "ref.zarr"
    build_store(BuildConfig(root=tree, out=ref, gts=tree / "gts", block_samples=2, progress=False))
    tree, gate = gated_tree(tree, tmp_path / "g", 1, 2)  # store index 10: block 5 of 8
    url = f"s3://{BUCKET}/kill.zarr"
    cmd = [sys.executable, "-m", "cli.occdata_cli", *_args(tree, url, "--workers", "2")]
    proc = subprocess.Popen(cmd, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    fd = gate.wait_reader()  # a worker converts block 5: mid-build
    assert proc.poll() is None, proc.communicate()
    family = [proc.pid, *descendants(proc.pid)]
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    gone = wait_for(lambda: not any(alive(p) for p in family), 15)
    os.close(fd)  # only now: an EOF would have given the blocked worker a truncated image
    assert gone, [p for p in family if alive(p)]
    s3.invalidate_cache()
    done = threading.Event()
    gate.serve(done.is_set)
    try:
        code, text = _cli(*_args(tree, url, "--workers", "2", "--resume"))
    finally:
        done.set()
    assert code == 0, text
    assert store_digest(url) == store_digest(ref)  # type: ignore[arg-type]
    code, text = _cli("verify", "--store", url, "--no-progress")
    assert code == 0, text
