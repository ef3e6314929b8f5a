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
from occdata.runtime.lock import StoreLockedError, store_lock
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
