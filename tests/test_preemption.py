"""Cluster-job behaviour (issue 17): stop signals save and resume bit-identically, no orphaned loader
processes, one writer per run folder. CLI subprocesses on the session's 2 x 3-sample synthetic store."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from gates import Gate
from proc_tools import alive, descendants, free_port, loader_processes, wait_for

from fastocc.checkpoint import load_checkpoint, save_checkpoint
from fastocc.model import FastOcc
from fastocc.train import load_config
from fastocc.train.config import config_to_toml
from fastocc.train.loop import TEST_GATE_ENV
from fastocc.train.preempt import EXIT_PREEMPTED
from fastocc.train.runlock import RunFolderBusy, RunLock

REPO = Path(__file__).resolve().parents[1]
TINY = {"input_hw": [64, 176], "epochs": 2, "lr": 2e-3, "lr_scaling": "none", "workers": 0, "threads": 1,
        "log_every": 1, "val_every": 0, "keep_epochs": 1, "ema": True}
ORPHAN_SECONDS = 10.0


def _toml(path: Path, **fields: object) -> Path:
    path.write_text(config_to_toml(load_config(None, {**TINY, **fields})))
    return path


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}


def _start(args: list[str], module_args: tuple[str, ...] = ("-m", "cli.fastocc_cli")) -> subprocess.Popen:
    """A CLI run in its own process group (so the test can signal the group, as a scheduler does)."""
    return subprocess.Popen([sys.executable, *module_args, *args], cwd=REPO, env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _train_records(out: Path) -> list[dict]:
    path = out / "metrics.jsonl"
    if not path.exists():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]


def _wait_steps(proc: subprocess.Popen, out: Path, steps: int, timeout: float = 600) -> None:
    ok = wait_for(lambda: proc.poll() is not None or sum(r["kind"] == "train" for r in _train_records(out)) >= steps,
                  timeout)
    if proc.poll() is not None or not ok:
        proc.kill()
        raise AssertionError(f"run ended or stalled before step {steps}:\n{proc.communicate()[0]}")


def _weights(path: Path) -> dict[str, torch.Tensor]:
    ck = load_checkpoint(path)
    return {**{f"model.{k}": v for k, v in ck.model.items()}, **{f"ema.{k}": v for k, v in (ck.ema or {}).items()}}


def _assert_identical(a: Path, b: Path) -> None:
    wa, wb = _weights(a), _weights(b)
    assert wa.keys() == wb.keys()
    diff = [k for k in wa if not torch.equal(wa[k], wb[k])]
    assert not diff, f"{len(diff)} tensors differ, e.g. {diff[:3]}"


def _assert_no_orphans(pids: list[int], log: str, torchrun: bool = False) -> None:
    assert wait_for(lambda: not any(alive(p) for p in pids), ORPHAN_SECONDS), \
        f"still alive {ORPHAN_SECONDS:g} s after the parent: {[p for p in pids if alive(p)]}"
    assert "leaked semaphore" not in log, log
    # torchrun's agent itself prints a SignalException traceback when it gets SIGTERM (not ours to change)
    tracebacks = log.split("Traceback (most recent call last):")[1:]
    assert all(torchrun and "SignalException" in t for t in tracebacks), log


# -- preemption: one process ----------------------------------------------------------------------------
def test_sigterm_to_the_process_group_saves_resumes_identically_and_leaves_no_orphans(
        synth_store: Path, tmp_path: Path) -> None:
    """Was: exit 143 with no last.pt (all progress lost), forkserver + workers orphaned, leaked semaphores."""
    conf = _toml(tmp_path / "c.toml", workers=2)
    base = ["train", "--store", str(synth_store), "--config", str(conf), "--no-progress"]
    ref = _start([*base, "--out", str(tmp_path / "ref")])
    log = ref.communicate()[0]
    assert ref.returncode == 0, log
    out = tmp_path / "term"
    proc = _start([*base, "--out", str(out)])
    _wait_steps(proc, out, 1)  # mid-epoch 1 (3 steps per epoch)
    loader = loader_processes(proc.pid)
    assert len(loader) >= 2, f"expected a forkserver and its workers, got {loader}"
    os.killpg(proc.pid, signal.SIGTERM)  # the whole group: trainer, forkserver, workers, resource tracker
    log = proc.communicate(timeout=120)[0]
    assert proc.returncode == EXIT_PREEMPTED, log
    assert "SIGTERM: saving" in log and "continue with --resume" in log
    _assert_no_orphans(loader, log)
    meta = load_checkpoint(out / "last.pt").meta
    assert 1 <= meta["opt_steps"] < 6
    res = _start([*base, "--out", str(out), "--resume"])
    log = res.communicate()[0]
    assert res.returncode == 0, log
    _assert_identical(tmp_path / "ref" / "last.pt", out / "last.pt")
    assert [r["opt_step"] for r in _train_records(out)] == [r["opt_step"] for r in _train_records(tmp_path / "ref")]


def test_warning_signal_stops_at_a_step_boundary(synth_store: Path, tmp_path: Path) -> None:
    """SIGUSR1 (SLURM's --signal=USR1@90) to the trainer alone: saves at the next step and exits 143."""
    conf = _toml(tmp_path / "c.toml", epochs=3)
    out = tmp_path / "usr1"
    proc = _start(["train", "--store", str(synth_store), "--config", str(conf), "--no-progress", "--out", str(out)])
    _wait_steps(proc, out, 1)
    proc.send_signal(signal.SIGUSR1)
    log = proc.communicate(timeout=120)[0]
    assert proc.returncode == EXIT_PREEMPTED, log
    assert "SIGUSR1: saving" in log
    steps = [r["opt_step"] for r in _train_records(out) if r["kind"] == "train"]
    assert load_checkpoint(out / "last.pt").meta["opt_steps"] == steps[-1] < 9  # the last finished step


# -- preemption: torchrun -------------------------------------------------------------------------------
def _rank_pids(agent: int) -> dict[int, int]:
    """{rank: pid} of torchrun's worker processes (from their environment)."""
    out = {}
    for pid in descendants(agent):
        try:
            env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"TORCHELASTIC_RUN_ID" not in b"".join(env) or "forkserver" in Path(f"/proc/{pid}/cmdline").read_text():
            continue
        ranks = [e.split(b"=", 1)[1] for e in env if e.startswith(b"RANK=")]
        if ranks:
            out.setdefault(int(ranks[0]), pid)
    return out


@pytest.mark.slow
def test_torchrun_ranks_agree_on_the_stop_step(synth_store: Path, tmp_path: Path) -> None:
    """2 gloo processes. SIGUSR1 to rank 1 only: both ranks stop after the same step, rank 0 writes
    last.pt, nobody blocks; then SIGTERM to the whole group of a resumed run; the final resume matches
    an uninterrupted torchrun run bit for bit, and `done:` is printed once."""
    conf = _toml(tmp_path / "c.toml", limit_train_samples=4, batch_size=2, epochs=3, workers=1)
    port = str(free_port())
    run = ["-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", port, "-m", "cli.fastocc_cli"]
    base = ["train", "--store", str(synth_store), "--config", str(conf), "--no-progress"]
    ref = _start([*base, "--out", str(tmp_path / "ref")], tuple(run))
    log = ref.communicate(timeout=600)[0]
    assert ref.returncode == 0, log
    assert log.count("done:") == 1, log
    out = tmp_path / "dist"
    proc = _start([*base, "--out", str(out)], tuple(run))
    _wait_steps(proc, out, 1)
    ranks = _rank_pids(proc.pid)
    assert sorted(ranks) == [0, 1], ranks
    os.kill(ranks[1], signal.SIGUSR1)
    log = proc.communicate(timeout=300)[0]
    assert "a stop signal on another rank: saving" in log, log  # rank 0 heard it through the all-reduce
    first = load_checkpoint(out / "last.pt").meta["opt_steps"]
    assert 1 <= first < 6
    proc = _start([*base, "--out", str(out), "--resume"], tuple(run))
    _wait_steps(proc, out, first + 1)
    loader = [p for r in _rank_pids(proc.pid).values() for p in loader_processes(r)]
    os.killpg(proc.pid, signal.SIGTERM)
    log = proc.communicate(timeout=300)[0]
    assert "SIGTERM: saving" in log, log
    _assert_no_orphans(loader, log, torchrun=True)
    assert load_checkpoint(out / "last.pt").meta["opt_steps"] > first
    proc = _start([*base, "--out", str(out), "--resume"], tuple(run))
    log = proc.communicate(timeout=600)[0]
    assert proc.returncode == 0, log
    assert log.count("done:") == 1, log
    _assert_identical(tmp_path / "ref" / "last.pt", out / "last.pt")


# -- no orphans: eval / predict / kill -9 ---------------------------------------------------------------
@pytest.fixture(scope="module")
def nano_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = load_config(None, {"input_hw": [64, 176]}).model_config()
    path = tmp_path_factory.mktemp("ckpt") / "nano.pt"
    save_checkpoint(path, cfg, FastOcc(cfg).state_dict())
    return path


@pytest.mark.parametrize(("command", "sig"), [
    ("predict", signal.SIGTERM), ("predict", signal.SIGKILL), ("eval", signal.SIGTERM),
    pytest.param("predict", signal.SIGINT, marks=pytest.mark.slow),
    pytest.param("eval", signal.SIGKILL, marks=pytest.mark.slow),
    pytest.param("eval", signal.SIGINT, marks=pytest.mark.slow),
])
def test_no_orphans_after_eval_or_predict_is_stopped(synth_store: Path, nano_ckpt: Path, tmp_path: Path,
                                                      command: str, sig: signal.Signals) -> None:
    """Was: SIGTERM to `fastocc predict --workers 2` left the forkserver and the workers running."""
    extra = ["--out", str(tmp_path / "pred")] if command == "predict" else ["--no-rayiou"]
    proc = _start([command, "--checkpoint", str(nano_ckpt), "--store", str(synth_store), "--split", "train",
                   "--workers", "2", "--no-progress", *extra])
    assert wait_for(lambda: proc.poll() is not None or len(loader_processes(proc.pid)) >= 3, 300), \
        proc.communicate()[0]
    loader = loader_processes(proc.pid)
    assert proc.poll() is None and len(loader) >= 3, loader
    (os.killpg if sig == signal.SIGINT else os.kill)(proc.pid, sig)  # Ctrl-C reaches the whole group
    log = proc.communicate(timeout=60)[0]
    assert proc.returncode != 0
    if sig == signal.SIGKILL:
        assert wait_for(lambda: not any(alive(p) for p in loader), ORPHAN_SECONDS), [p for p in loader if alive(p)]
    else:
        _assert_no_orphans(loader, log)


def test_kill9_of_the_trainer_leaves_no_orphans(synth_store: Path, tmp_path: Path) -> None:
    """Was: after kill -9 the forkserver and both workers kept running with parent PID 1."""
    conf = _toml(tmp_path / "c.toml", workers=2, epochs=5)
    out = tmp_path / "k9"
    proc = _start(["train", "--store", str(synth_store), "--config", str(conf), "--no-progress", "--out", str(out)])
    _wait_steps(proc, out, 1)
    loader = loader_processes(proc.pid)
    assert len(loader) >= 2, loader
    proc.kill()
    proc.communicate()
    assert wait_for(lambda: not any(alive(p) for p in loader), ORPHAN_SECONDS), [p for p in loader if alive(p)]


# -- one writer per run folder --------------------------------------------------------------------------
def test_second_trainer_on_the_same_out_is_refused_naming_the_holder(synth_store: Path, tmp_path: Path) -> None:
    """Was: two trainers started 1 s apart both ran, every metrics record twice."""
    out = tmp_path / "dup"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from fastocc.train.runlock import RunLock\n"
                               f"with RunLock({str(out)!r}):\n    print('locked', flush=True); time.sleep(600)"],
                              cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        proc = subprocess.run([sys.executable, "-m", "cli.fastocc_cli", "train", "--store", str(synth_store),
                               "--out", str(out), "--no-progress"], cwd=REPO, env=_env(), capture_output=True,
                              text=True, timeout=300)
        assert proc.returncode == 1
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, proc.stderr
        assert f"PID {holder.pid} on host {socket.gethostname()}" in lines[0] and "in use" in lines[0]
        assert not (out / "metrics.jsonl").exists() and not (out / "config.toml").exists()
    finally:
        holder.kill()  # SIGKILL: the kernel releases the lock
        holder.wait()
    with RunLock(out):  # free again
        with pytest.raises(RunFolderBusy, match=f"PID {os.getpid()} on host"):
            RunLock(out).__enter__()


def test_stale_temporaries_of_an_interrupted_save_are_removed(tmp_path: Path) -> None:
    """Was: kill -9 during a save left a hidden `.last.pt.<random>.tmp` (7.5 MB) forever."""
    out = tmp_path / "run"
    out.mkdir()
    stale = [out / ".last.pt.k2j3h4.tmp", out / ".epoch_002.pt.abcdef.tmp"]
    for p in stale:
        p.write_bytes(b"x" * 1000)
    keep = out / "notes.tmp"
    keep.write_text("mine")
    with RunLock(out) as lock:
        assert sorted(lock.removed) == sorted(stale)
    assert not any(p.exists() for p in stale) and keep.exists()


def test_stop_signal_before_the_first_step_saves_step_zero(synth_store: Path, tmp_path: Path) -> None:
    """SIGTERM during start-up: the handler is in place from the start, last.pt holds step 0, exit 143.
    The trainer blocks on a FIFO (FASTOCC_TEST_GATE) right after installing it, until the signal is sent."""
    conf = _toml(tmp_path / "c.toml")
    out = tmp_path / "early"
    gate = Gate(tmp_path / "gate", b"")
    proc = subprocess.Popen([sys.executable, "-m", "cli.fastocc_cli", "train", "--store", str(synth_store),
                             "--config", str(conf), "--no-progress", "--out", str(out)], cwd=REPO,
                            env={**_env(), TEST_GATE_ENV: str(gate.path)}, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    fd = gate.wait_reader()
    proc.send_signal(signal.SIGTERM)
    gate.release(fd)
    log = proc.communicate(timeout=300)[0]
    assert proc.returncode == EXIT_PREEMPTED, log
    assert "SIGTERM: saving" in log, log
    assert load_checkpoint(out / "last.pt").meta["opt_steps"] == 0
    assert not [r for r in _train_records(out) if r["kind"] == "train"]
