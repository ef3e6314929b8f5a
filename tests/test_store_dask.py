"""Issue 24: `occdata build` on Dask: many writers, same bytes, workers and clients that die.

The reference is a build run in this process (one worker, no cluster); every other build must
give the same arrays byte for byte (`store_digest`) and pass `occdata verify`. One 2-worker
LocalCluster is shared by the tests of this module (start-up costs seconds).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from gates import Gate, gated_tree
from proc_tools import alive, descendants, wait_for
from replicated_tree import make_replicated_tree
from test_store_build import store_digest

from cli.occdata_cli import main
from occdata.errors import OccDataError
from occdata.fileio import is_temp_name
from occdata.runtime.cluster import ClusterConfig, cluster_client, run_tasks
from occdata.store.build import BuildConfig, build_store
from occdata.store.plan import block_spans, plan_regions, relocate

REPO = Path(__file__).resolve().parents[1]
N = 24  # samples: 6 blocks of 4


@pytest.fixture(scope="module")
def tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory) -> Path:
    return make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory.mktemp("dk") / "ns", 2, N // 2)


@pytest.fixture(scope="module")
def reference(tree, tmp_path_factory) -> dict[str, str]:
    out = tmp_path_factory.mktemp("ref") / "ref.zarr"
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=4, progress=False))
    return store_digest(out)


@pytest.fixture(scope="module")
def client():
    with cluster_client(ClusterConfig(workers=2)) as c:
        yield c


def _config(tree: Path, out: Path | str, **kw) -> BuildConfig:
    return BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=4, progress=False, **kw)


def _verify(out: Path | str) -> None:
    r = CliRunner().invoke(main, ["verify", "--store", str(out), "--no-progress"])
    assert r.exit_code == 0, r.output


def _committed(path: Path) -> int:
    try:
        return int((zarr.open_group(str(path), mode="r")["status/state"][:] != 0).sum())
    except Exception:  # noqa: BLE001 - not created yet
        return 0


# --- the task runner alone -------------------------------------------------------------------------
@dataclass(frozen=True)
class _Square:
    x: int
    units: int = 1

    def run(self, should_stop) -> int:
        return self.x * self.x


def test_run_tasks_follow_ups_and_keep(client) -> None:
    """Follow-up tasks run, dropped ones do not, every result reaches on_result once."""
    for c in (None, client):
        seen: list[tuple[int, int]] = []

        def on_result(t: _Square, r: int, seen=seen) -> list[_Square]:
            seen.append((t.x, r))
            return [_Square(t.x + 100)] if t.x < 3 else []

        run_tasks(c, [_Square(x) for x in range(6)], desc="t", progress=False, on_result=on_result,
                  keep=lambda t: t.x != 4)
        assert sorted(seen) == sorted([(t, t * t) for t in (0, 1, 2, 3, 5, 100, 101, 102)])


def test_plan_regions_then_relocate_blocks_that_outgrew_them() -> None:
    """Hand-computed: chunk sizes from the layout (1 MiB of JPEG, 65536 depth rows); 3 blocks of 2
    samples. Regions follow each other chunk-aligned; a relocated block goes after the end, in block
    order, and keeps its other array's region."""
    mib, rows = 1 << 20, 1 << 16
    bounds = np.array([[10, 5], [mib, 0], [0, 0], [0, 0], [mib + 1, rows + 1], [1, 1]], dtype=np.int64)
    regions = plan_regions(bounds, block_spans(6, 2))
    assert regions[:, 0].tolist() == [[0, 2 * mib], [2 * mib, 2 * mib], [2 * mib, 4 * mib]]
    assert regions[:, 1].tolist() == [[0, rows], [rows, rows], [rows, 3 * rows]]
    moved = relocate(regions, {2: (5 * mib, 1), 0: (mib, 2 * rows)})
    assert moved[0].tolist() == [[0, 2 * mib], [3 * rows, 5 * rows]]  # JPEG still fits; depth moves
    assert moved[2].tolist() == [[4 * mib, 9 * mib], [rows, 3 * rows]]
    assert moved[1].tolist() == regions[1].tolist()


# --- many writers ------------------------------------------------------------------------------------
def test_two_workers_write_the_same_bytes_as_one(tree, reference, client, tmp_path) -> None:
    out = tmp_path / "two.zarr"
    report = build_store(_config(tree, out), client=client)
    assert report.n_done == N
    assert store_digest(out) == reference
    assert not Path(str(out) + ".staging").exists()
    _verify(out)


def test_kill9_of_one_worker_mid_build(tree, reference, client, tmp_path) -> None:
    """A worker killed while it converts a block (it is blocked reading a gated image of block 3):
    Dask reruns that task on a live worker, which reads the image again; same bytes."""
    root, gate = gated_tree(tree, tmp_path / "g", 1, 2)  # store index 14: block 3 of 6
    out = tmp_path / "wk.zarr"
    workers = set(client.run(os.getpid).values())
    result: dict[str, object] = {}

    def run() -> None:
        try:
            result["report"] = build_store(_config(root, out), client=client)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            result["error"] = exc

    t = threading.Thread(target=run)
    t.start()
    fd = gate.wait_reader()
    (victim,) = [p for p in gate.readers() if p in workers]
    os.kill(victim, signal.SIGKILL)
    # The retry opens the FIFO while this end is still open, so it blocks until the bytes come.
    retried = wait_for(lambda: any(p != victim for p in gate.readers()), 120, 0.01)
    gate.release(fd)
    t.join(180)
    assert retried, "the killed worker's block was never rerun"
    assert not t.is_alive() and "error" not in result, result.get("error")
    assert _committed(out) == N and store_digest(out) == reference
    _verify(out)
    assert wait_for(lambda: len(client.nthreads()) == 2, 30)  # the nanny started a new worker


# --- the client dies or is stopped -------------------------------------------------------------------
def _spawn(tree: Path, out: Path | str, *extra: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "cli.occdata_cli", "build", "--root", str(tree), "--gts", str(tree / "gts"),
           "--out", str(out), "--block-samples", "4", "--workers", "2", "--no-progress", *extra]
    env = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _resume(tree: Path, out: Path | str) -> None:
    r = CliRunner().invoke(main, ["build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(out),
                                  "--block-samples", "4", "--workers", "2", "--resume", "--no-progress"])
    assert r.exit_code == 0, r.output


def _resume_served(root: Path, out: Path | str, gate: Gate) -> None:
    done = threading.Event()
    gate.serve(done.is_set)
    try:
        _resume(root, out)
    finally:
        done.set()


def _mid_build(proc: subprocess.Popen, gate: Gate) -> tuple[int, list[int]]:
    """Once a worker of the build blocks on the gate: the gate's write end, and the build's processes
    (client + LocalCluster)."""
    fd = gate.wait_reader()
    assert proc.poll() is None, proc.communicate()
    return fd, [proc.pid, *descendants(proc.pid)]


@pytest.mark.timeout(300)
def test_kill9_of_the_client_leaves_no_process_then_resume(tree, reference, tmp_path) -> None:
    root, gate = gated_tree(tree, tmp_path / "g", 1, 2)
    out = tmp_path / "ck.zarr"
    proc = _spawn(root, out)
    fd, family = _mid_build(proc, gate)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    gone = wait_for(lambda: not any(alive(p) for p in family), 15)
    os.close(fd)  # only now: an EOF would have given the blocked worker a truncated image
    assert gone, [p for p in family if alive(p)]
    _resume_served(root, out, gate)
    assert store_digest(out) == reference
    _verify(out)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("target", ["client", "group"])
def test_sigterm_stops_then_resume(tree, reference, tmp_path, target: str) -> None:
    """SIGTERM to the client alone (`kill`), or to the whole process group (as SLURM sends it), while a
    worker converts block 3: exit 143 naming --resume, no process left; the resume gives the same bytes."""
    root, gate = gated_tree(tree, tmp_path / "g", 1, 2)
    out = tmp_path / "st.zarr"
    proc = _spawn(root, out)
    fd, family = _mid_build(proc, gate)
    if target == "client":
        os.kill(proc.pid, signal.SIGTERM)
    else:
        os.killpg(proc.pid, signal.SIGTERM)
    gate.release(fd)  # the read in flight completes (or its worker is gone)
    gate.serve(lambda: proc.poll() is not None)
    _, err = proc.communicate(timeout=120)  # a hang guard, not a speed limit
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "--resume" in err, err
    assert wait_for(lambda: not any(alive(p) for p in family), 15)
    # Stopped before the final commit. (Blocks commit in any order: the other worker may have committed
    # every block but the gated one, and the gated read, released above, may finish too.)
    assert zarr.open_group(str(out), mode="r").attrs.get("complete") is not True
    _resume_served(root, out, gate)
    assert store_digest(out) == reference
    assert not [p for p in out.rglob("*") if is_temp_name(p.name)]  # a killed write's temporary is gone


# --- schedulers that cannot be reached or go away ----------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_line(tree, tmp_path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "2s"}
    r = subprocess.run([sys.executable, "-m", "cli.occdata_cli", "build", "--root", str(tree), "--out",
                        str(tmp_path / "u.zarr"), "--scheduler", f"tcp://127.0.0.1:{_free_port()}", "--no-progress"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr and "cannot reach the Dask scheduler at tcp://127.0.0.1:" in r.stderr
    assert len([ln for ln in r.stderr.splitlines() if ln.strip()]) == 1, r.stderr


@pytest.mark.timeout(300)
def test_scheduler_that_goes_away_is_one_line(tree, reference, tmp_path) -> None:
    """An external scheduler + worker (the `dask` commands); the scheduler is killed mid-build."""
    port = _free_port()
    dask_cmd = [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                "--no-dashboard"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    sched = subprocess.Popen(dask_cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://127.0.0.1:{port}",
                               "--nthreads", "1", "--no-dashboard", "--death-timeout", "10"],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    root, gate = gated_tree(tree, tmp_path / "g", 1, 2)
    out = tmp_path / "sg.zarr"
    try:
        proc = _spawn(root, out, "--scheduler", f"tcp://127.0.0.1:{port}")
        fd, _ = _mid_build(proc, gate)  # the external worker converts block 3
        sched.kill()
        gate.release(fd)
        gate.serve(lambda: proc.poll() is not None)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 1 and "Traceback" not in err, err
        assert "lost the Dask scheduler at tcp://127.0.0.1:" in err, err
        assert len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
        _resume_served(root, out, gate)
        assert store_digest(out) == reference
    finally:
        for p in (sched, worker):
            p.kill()
            p.wait()


def test_scheduler_option_is_validated() -> None:
    with pytest.raises(OccDataError, match="expected an address"):
        ClusterConfig(scheduler="nohost")
    with pytest.raises(OccDataError, match="--workers"):
        ClusterConfig(workers=0)


def test_on_error_fail_commits_everything_before_the_bad_sample(tree, client, tmp_path) -> None:
    """A truncated JPEG in sample 9 (block 2): samples 0..8 commit, 9..11 (the rest of its block) stay
    pending, and the message names sample 9; blocks after it commit only if they finished before the
    failure came back (tasks commit in any order), and are never half done; after the fix, --resume
    completes."""
    import json
    import shutil

    from replicated_tree import _tok

    bad_tree = tmp_path / "bad"
    shutil.copytree(tree, bad_tree, symlinks=True)
    table = bad_tree / "v1.0-mini" / "sample_data.json"
    sds = json.loads(table.read_text())
    token9 = _tok("replay-0000", 9)  # scene 0 holds store indices 0..11
    row = next(r for r in sds if r["sample_token"] == token9 and r["filename"].endswith(".jpg"))
    good = (bad_tree / row["filename"]).read_bytes()
    row["filename"] = "samples/broken.jpg"
    table.write_text(json.dumps(sds))
    (bad_tree / "samples" / "broken.jpg").write_bytes(good[: len(good) // 2])
    out = tmp_path / "f.zarr"
    with pytest.raises(OccDataError, match=f"sample 9 \\({token9}\\) failed"):
        build_store(_config(bad_tree, out), client=client)
    state = zarr.open_group(str(out), mode="r")["status/state"][:]
    assert (state[:9] == 1).all() and (state[9:12] == 0).all()
    assert all(len(set(state[i0 : i0 + 4])) == 1 for i0 in range(12, N, 4))
    (bad_tree / "samples" / "broken.jpg").write_bytes(good)
    report = build_store(_config(bad_tree, out, resume=True), client=client)
    assert report.n_done == N
    _verify(out)


def test_resume_converts_only_the_blocks_not_committed(tree, reference, tmp_path, monkeypatch) -> None:
    """A run stopped by a failing task in block 2 (one worker: blocks in order): blocks 0 and 1 are
    committed with their payload in place; --resume converts blocks 2..5 only; same bytes."""
    import occdata.store.blocks as blocks

    out = tmp_path / "rs.zarr"
    real_convert = blocks.convert_block

    def stop_at_block_2(job):
        if job.block == 2:
            raise RuntimeError("stopped in block 2")
        return real_convert(job)

    monkeypatch.setattr(blocks, "convert_block", stop_at_block_2)
    with pytest.raises(RuntimeError, match="block 2"):
        build_store(_config(tree, out))
    assert _committed(out) == 8
    assert not Path(str(out) + ".staging").exists()
    converted: list[int] = []

    def counting_convert(job):
        converted.append(job.block)
        return real_convert(job)

    monkeypatch.setattr(blocks, "convert_block", counting_convert)
    build_store(_config(tree, out, resume=True))
    assert converted == [2, 3, 4, 5]
    assert store_digest(out) == reference
    _verify(out)


@pytest.mark.parametrize("exc_name", ["CommClosedError", "FutureCancelledError", "CancelledError", "asyncio",
                                      "ConnectionResetError", "TimeoutError", "ConnectTimeout", "ClosedClientError"])
def test_every_way_of_losing_the_scheduler_says_the_same_line(exc_name: str) -> None:
    """Whichever call notices first (a result's gather, a cancelled future), one message with the
    address: the exceptions distributed really raises (a task's own error comes back as TaskFailed)."""
    import asyncio
    import concurrent.futures
    from types import SimpleNamespace

    from distributed.client import ClosedClientError, FutureCancelledError
    from distributed.comm.core import CommClosedError

    from occdata.runtime.cluster import _result

    exc = {"CommClosedError": CommClosedError("in <TCP (closed) ConnectionPool.gather>: Stream is closed"),
           "FutureCancelledError": FutureCancelledError("k", "scheduler-connection-lost"),
           "CancelledError": concurrent.futures.CancelledError(), "asyncio": asyncio.CancelledError(),
           "ConnectionResetError": ConnectionResetError(104, "Connection reset by peer"),
           "TimeoutError": TimeoutError(),
           "ConnectTimeout": OSError("Timed out trying to connect to tcp://127.0.0.1:1 after 30 s"),
           "ClosedClientError": ClosedClientError("Client is closed. Can't send update-graph message.")}[exc_name]

    def boom() -> None:
        raise exc

    with pytest.raises(OccDataError, match=r"^lost the Dask scheduler at tcp://127.0.0.1:1 \(.*--resume$"):
        _result(SimpleNamespace(result=boom), "tcp://127.0.0.1:1")


# --- errors that are not a lost scheduler (issue 40, item 3) -----------------------------------------
_LOST = "lost the Dask scheduler"


@dataclass(frozen=True)
class _HoldsALock:
    """A task that does not pickle (Dask pickles a task when it is submitted)."""

    lock: object
    units: int = 1

    def run(self, should_stop) -> int:
        return 0


@dataclass(frozen=True)
class _ReturnsALock:
    """A task whose result does not pickle: the worker fails to send it back (not a TaskFailed)."""

    units: int = 1

    def run(self, should_stop) -> object:
        return threading.Lock()


def test_a_task_that_does_not_pickle_is_named_not_a_lost_scheduler(client) -> None:
    with pytest.raises(OccDataError) as info:
        run_tasks(client, [_Square(1), _HoldsALock(threading.Lock())], desc="t", progress=False)
    text = str(info.value)
    assert _LOST not in text and "--resume" not in text, text
    assert text.startswith("submitting a t task (_HoldsALock) failed: TypeError:"), text
    assert "cannot pickle '_thread.lock' object" in text and "\n" not in text, text


def test_a_result_that_does_not_pickle_is_named_not_a_lost_scheduler(client) -> None:
    with pytest.raises(OccDataError) as info:
        run_tasks(client, [_ReturnsALock()], desc="t", progress=False)
    text = str(info.value)
    assert _LOST not in text and "--resume" not in text, text
    assert text.startswith("a t task (_ReturnsALock) failed: TypeError: Could not serialize object of type lock"), text
    assert "\n" not in text, text


def test_a_bug_in_submit_is_named_and_the_committed_blocks_stay(tree, reference, client, tmp_path,
                                                                monkeypatch) -> None:
    """`client.submit` raising ValueError at the 6th of 6 blocks (a bug on the client side, after at
    least two blocks came back: the window is 4): one line naming it, not resume advice; the blocks
    committed before stay committed, and --resume then completes with the same bytes."""
    out = tmp_path / "sb.zarr"
    real_submit = client.submit
    calls = [0]

    def submit(*args, **kw):
        calls[0] += 1
        if calls[0] == 6:
            raise ValueError("planted bug in submit")
        return real_submit(*args, **kw)

    monkeypatch.setattr(client, "submit", submit)
    with pytest.raises(OccDataError) as info:
        build_store(_config(tree, out), client=client)
    text = str(info.value)
    assert _LOST not in text, text
    assert text.startswith("submitting a build task (ConvertJob) failed: ValueError: planted bug in submit at "
                           "test_store_dask.py:"), text
    assert text.endswith("everything committed so far is kept"), text
    monkeypatch.undo()
    state = zarr.open_group(str(out), mode="r")["status/state"][:]
    assert (state == 1).sum() >= 8 and all(len(set(state[i0 : i0 + 4])) == 1 for i0 in range(0, N, 4)), state
    build_store(_config(tree, out, resume=True), client=client)
    assert store_digest(out) == reference


@pytest.mark.parametrize("exc_name", ["TypeError", "RuntimeError", "FileNotFoundError", "KeyError"])
def test_errors_that_are_not_the_connections_are_not_a_lost_scheduler(exc_name: str) -> None:
    """What the cluster path raises besides a lost connection (a result that did not serialize, the
    scheduler failing to decode a task, a bug): named with its type, never resume advice."""
    from types import SimpleNamespace

    from occdata.runtime.cluster import _result

    exc = {"TypeError": TypeError("Could not serialize object of type lock", "<graph>"),
           "RuntimeError": RuntimeError("Error during deserialization of the task graph."),
           "FileNotFoundError": FileNotFoundError(2, "No such file or directory", "/x"),
           "KeyError": KeyError("k")}[exc_name]

    def boom() -> None:
        raise exc

    with pytest.raises(OccDataError) as info:
        _result(SimpleNamespace(result=boom), "tcp://127.0.0.1:1")
    text = str(info.value)
    assert _LOST not in text and "--resume" not in text, text
    assert text.startswith(f"a task failed: {exc_name}: "), text
    assert "in boom" in text and "<graph>" not in text, text
