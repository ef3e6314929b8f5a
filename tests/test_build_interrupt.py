"""Issue 12 item 9: one Ctrl-C stops `occdata build --workers 2` promptly and cleanly.

Ctrl-C in a terminal sends SIGINT to the whole foreground process group (the workers too); the
test does the same with `killpg`, at several moments of the build. Before the fix the pool's
shutdown hung in 2 of 11 trials and every worker printed a KeyboardInterrupt traceback.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zarr
from click.testing import CliRunner
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


def _interrupt_once(tree: Path, out: Path, moment: str) -> tuple[int | None, str, float]:
    cmd = [sys.executable, "-m", "cli.occdata_cli", "build", "--root", str(tree), "--gts", str(tree / "gts"),
           "--out", str(out), "--block-samples", "4", "--workers", "2", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, text=True)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        if (moment == "start" and out.exists()) or (moment == "first-block" and _committed(out) >= 4) or (
                moment == "mid" and _committed(out) >= N // 2):
            break
        time.sleep(0.01)
    t0 = time.monotonic()
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole group
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return None, "HUNG", 30.0
    return proc.returncode, err, time.monotonic() - t0


def _check(tree: Path, out: Path, reference: dict[str, str], moment: str) -> None:
    code, err, seconds = _interrupt_once(tree, out, moment)
    assert code is not None, f"build hung after Ctrl-C at {moment}"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    if code == 0:  # it finished before the signal: nothing to check but the result
        assert store_digest(out) == reference
        return
    assert code == 130, (code, err)
    assert "rerun the same command with --resume" in err
    assert seconds < 15, f"took {seconds:.1f} s to stop"
    assert _committed(out) < N
    r = CliRunner().invoke(main, ["build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(out),
                                  "--block-samples", "4", "--workers", "2", "--resume", "--no-progress"])
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
