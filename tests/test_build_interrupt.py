"""Issue 12 item 9: one Ctrl-C stops `occdata build --workers 2` promptly and cleanly.

Ctrl-C in a terminal sends SIGINT to the whole foreground process group (the workers too); the
test does the same with `killpg`, at several moments of the build. The last sample's image is a FIFO
gate (tests/gates.py), so the build cannot have finished when the signal comes. Before the fix the pool's
shutdown hung in 2 of 11 trials and every worker printed a KeyboardInterrupt traceback.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zarr
from click.testing import CliRunner
from gates import Gate, gated_tree
from proc_tools import wait_for
from replicated_tree import make_replicated_tree
from test_store_build import store_digest

from cli.occdata_cli import main
from occdata.store.build import BuildConfig, build_store

REPO = Path(__file__).resolve().parents[1]
N = 40


@pytest.fixture(scope="module")
def tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory) -> Path:
    return make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory.mktemp("int") / "ns", 2, N // 2)


@pytest.fixture(scope="module")
def reference(tree, tmp_path_factory) -> dict[str, str]:
    out = tmp_path_factory.mktemp("ref") / "ref.zarr"
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=4, progress=False))
    return store_digest(out)


def _committed(path: Path) -> int:
    try:
        return int((zarr.open_group(str(path), mode="r")["status/state"][:] != 0).sum())
    except Exception:  # noqa: BLE001 - not created yet
        return 0


def _serve_while(gate: Gate, proc: subprocess.Popen) -> None:
    gate.serve(lambda: proc.poll() is not None)


def _interrupt_once(root: Path, gate: Gate, out: Path, moment: str) -> tuple[int | None, str]:
    """Ctrl-C at `moment`; the last block (sample N-1 is a FIFO gate) cannot finish before it."""
    cmd = [sys.executable, "-m", "cli.occdata_cli", "build", "--root", str(root), "--gts", str(root / "gts"),
           "--out", str(out), "--block-samples", "4", "--workers", "2", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, text=True)
    reached = {"start": lambda: out.exists(), "first-block": lambda: _committed(out) >= 4,
               "mid": lambda: _committed(out) >= N // 2}[moment]
    ok = wait_for(lambda: proc.poll() is not None or reached(), 300, 0.01)
    assert ok and proc.poll() is None, f"the build ended or stalled before {moment}: {proc.communicate()}"
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole group
    _serve_while(gate, proc)  # a read of the gated image in flight or still to come completes
    try:
        _, err = proc.communicate(timeout=120)  # a hang guard, not a speed limit
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return None, "HUNG"
    return proc.returncode, err


def _check(tree: Path, out: Path, reference: dict[str, str], moment: str) -> None:
    root, gate = gated_tree(tree, out.parent / f"{out.stem}-tree", 1, N // 2 - 1)  # the last sample
    code, err = _interrupt_once(root, gate, out, moment)
    assert code is not None, f"build hung after Ctrl-C at {moment}"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert code == 130, (code, err)
    assert "rerun the same command with --resume" in err
    assert _committed(out) < N
    done = threading.Event()
    gate.serve(done.is_set)
    try:
        r = CliRunner().invoke(main, ["build", "--root", str(root), "--gts", str(root / "gts"), "--out", str(out),
                                      "--block-samples", "4", "--workers", "2", "--resume", "--no-progress"])
    finally:
        done.set()
    assert r.exit_code == 0, r.output
    assert store_digest(out) == reference


@pytest.mark.timeout(300)
@pytest.mark.parametrize("moment", ["start", "first-block", "mid"])
def test_ctrl_c_stops_promptly_and_resumes_identically(tree, reference, tmp_path, moment) -> None:
    _check(tree, tmp_path / "c.zarr", reference, moment)


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("rep", range(4))
@pytest.mark.parametrize("moment", ["start", "first-block", "mid"])
def test_ctrl_c_repeated(tree, reference, tmp_path, moment, rep) -> None:
    _check(tree, tmp_path / f"r{rep}.zarr", reference, moment)
