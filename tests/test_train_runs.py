"""Issue 17: runs that grow (--init-from, more --epochs on --resume), checkpoint messages, file modes
follow the umask, collective timeouts, and the small things (poses, broken pipe, labelled figures)."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import stat
import subprocess
import sys
import textwrap
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from proc_tools import free_port

from fastocc.checkpoint import CheckpointError, load_checkpoint, load_model, save_checkpoint
from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader
from fastocc.data.dataset import loader_batches
from fastocc.deploy import DeployError, Predictor, synthetic_rig
from fastocc.model import FastOcc
from fastocc.model.config import preset
from fastocc.train import ConfigError, TrainConfig, load_config, train
from fastocc.train.config import config_to_toml, incompatible_fields
from fastocc.train.loop import _val_text
from occdata.errors import OccDataError
from occdata.store.reader import open_store

REPO = Path(__file__).resolve().parents[1]
TINY = {"input_hw": [64, 176], "epochs": 1, "lr": 2e-3, "lr_scaling": "none", "workers": 0, "threads": 1,
        "log_every": 1, "val_every": 0, "keep_epochs": 1, "ema": True}


def _cfg(store: Path, out: Path, **fields: object) -> TrainConfig:
    return load_config(None, {**TINY, "store": str(store), "out": str(out), **fields})


def _records(out: Path, kind: str = "train") -> list[dict]:
    return [r for r in map(json.loads, (out / "metrics.jsonl").read_text().splitlines()) if r["kind"] == kind]


# -- runs that grow -------------------------------------------------------------------------------------
def test_init_from_loads_model_and_ema(synth_store: Path, tmp_path: Path) -> None:
    """A new run from run A's weights: after one step at lr 1e-12 the model is A's model and the EMA is
    d A_ema + (1 - d) A_model with d = min(0.999, 2/11) (the ramp restarts: update 1)."""
    src = tmp_path / "a"
    train(_cfg(synth_store, src, limit_train_samples=1), progress=False)
    a = load_checkpoint(src / "last.pt")
    out = tmp_path / "b"
    train(_cfg(synth_store, out, limit_train_samples=1, lr=1e-12, init_from=str(src / "last.pt")), progress=False)
    b = load_checkpoint(out / "last.pt")
    params = {n for n, _ in FastOcc(a.model_config).named_parameters()}
    d = 2 / 11
    worst_model = max(float((b.model[k] - a.model[k]).abs().max()) for k in params)
    worst_ema = max(float((b.ema[k] - (d * a.ema[k] + (1 - d) * a.model[k])).abs().max()) for k in params)
    assert worst_model < 1e-6 and worst_ema < 1e-6, (worst_model, worst_ema)
    gap = max(float((a.ema[k] - a.model[k]).abs().max()) for k in params)
    assert gap > 1e-4  # A's EMA differs from its model, so the EMA check can fail
    with pytest.raises(OccDataError, match="cannot be combined with --resume"):
        train(_cfg(synth_store, out, init_from=str(src / "last.pt")), resume=True, progress=False)
    other = tmp_path / "other.pt"
    tiny = preset("tiny", input_hw=(64, 176))
    save_checkpoint(other, tiny, FastOcc(tiny).state_dict())
    with pytest.raises(CheckpointError, match=r"first difference at key '.*': checkpoint \(\d+.*\), model \(\d+"):
        train(_cfg(synth_store, tmp_path / "c", init_from=str(other)), progress=False)


def test_epochs_may_grow_on_resume_and_the_cosine_is_stretched(synth_store: Path, tmp_path: Path) -> None:
    """1 epoch, then --resume with 2: the learning rate of every new step is lr_at(samples_seen) of the
    2-epoch schedule (the cosine stretched to the new end, as if planned so); fewer epochs are refused."""
    out = tmp_path / "grow"
    cfg = _cfg(synth_store, out, warmup_epochs=0.0)
    train(cfg, progress=False)
    first = _records(out)
    assert [r["opt_step"] for r in first] == [1, 2, 3]
    assert first[-1]["lr"] == pytest.approx(cfg.lr_at(2, 3))
    grown = replace(cfg, epochs=2)
    result = train(grown, resume=True, progress=False)
    assert (result.epochs_done, result.opt_steps) == (2, 6)
    recs = _records(out)
    assert [r["opt_step"] for r in recs] == [1, 2, 3, 4, 5, 6]
    for r in recs[3:]:
        assert r["lr"] == pytest.approx(grown.lr_at(r["samples_seen"] - 1, 3), rel=1e-12)
    assert recs[3]["lr"] == pytest.approx(cfg.peak_lr() * (1e-3 + (1 - 1e-3) * 0.5 * (1 + np.cos(np.pi * 3 / 6))))
    with pytest.raises(OccDataError, match=r"epochs: 2 -> 1\).*epochs may only grow"):
        train(cfg, resume=True, progress=False)


# -- checkpoint messages --------------------------------------------------------------------------------
def test_bad_last_pt_on_resume_is_one_line_pointing_to_the_newest_epoch_file(synth_store: Path,
                                                                             tmp_path: Path) -> None:
    out = tmp_path / "run"
    train(_cfg(synth_store, out, limit_train_samples=1, keep_epochs=2, epochs=2), progress=False)
    last = out / "last.pt"
    good = last.read_bytes()
    cases = {"truncated": good[: len(good) // 2], "not a checkpoint at all": os.urandom(4096), "truncated (an": b""}
    for what, data in cases.items():
        last.write_bytes(data)
        with pytest.raises(CheckpointError) as err:
            train(_cfg(synth_store, out, limit_train_samples=1, epochs=2), resume=True, progress=False)
        msg = str(err.value)
        assert str(last) in msg and what in msg and f"{out / 'epoch_002.pt'}" in msg, msg
        assert "weights_only" not in msg and "\n" not in msg
    payload = torch.load(out / "epoch_002.pt", weights_only=True)
    payload["version"] = 99
    torch.save(payload, last)
    with pytest.raises(CheckpointError, match="version 99 is from another fastocc version"):
        load_checkpoint(last)


def test_weights_that_do_not_fit_name_the_first_key_and_both_shapes(tmp_path: Path) -> None:
    """Was: "weights do not fit the model config (Error(s) in loading state_dict for FastOcc:)"."""
    nano, tiny = preset("nano"), preset("tiny")
    path = tmp_path / "mixed.pt"
    save_checkpoint(path, nano, FastOcc(tiny).state_dict())  # a config that does not match its weights
    with pytest.raises(CheckpointError) as err:
        load_model(path)
    msg = str(err.value)
    key = next(k for k, v in FastOcc(nano).state_dict().items() if v.shape != FastOcc(tiny).state_dict()[k].shape)
    want_ck, want_model = tuple(FastOcc(tiny).state_dict()[key].shape), tuple(FastOcc(nano).state_dict()[key].shape)
    assert f"key {key!r}: checkpoint {want_ck}, model {want_model}" in msg, msg


# -- file modes follow the umask ------------------------------------------------------------------------
def _modes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): stat.S_IMODE(p.stat().st_mode) for p in folder.rglob("*") if p.is_file()}


def test_written_files_follow_the_umask(synth_root: Path, synth_store: Path, tmp_path: Path) -> None:
    """Was: last.pt, labels.npz and pictures 0600 (mkstemp) while best.pt / epoch_*.pt were 0644."""
    from fastocc.infer.predict import PredictConfig
    from fastocc.infer.write import PredictRun, run_predict
    from occdata.store.build import BuildConfig, build_store

    old = os.umask(0o027)
    try:
        run = tmp_path / "run"
        train(_cfg(synth_store, run, limit_train_samples=1), progress=False)
        pred = tmp_path / "pred"
        run_predict(PredictRun(checkpoint=run / "last.pt", out=pred, png=1, progress=False,
                               predict=PredictConfig(store=synth_store, split="train")))
        store = tmp_path / "s.zarr"
        build_store(BuildConfig(root=synth_root, out=store, gts=synth_root / "gts", progress=False))
    finally:
        os.umask(old)
    for folder, must in ((run, ("last.pt", "epoch_001.pt", "config.toml", "metrics.jsonl", ".lock")),
                         (pred, ("labels.npz", ".png")), (store, ("zarr.json",))):
        modes = _modes(folder)
        for name in must:
            assert any(k.endswith(name) for k in modes), (name, sorted(modes))
        wrong = {k: oct(m) for k, m in modes.items() if m != 0o640}
        assert not wrong, wrong


# -- config: the [loss] table ---------------------------------------------------------------------------
def test_loss_weights_table_and_the_old_flat_keys(tmp_path: Path) -> None:
    new = tmp_path / "new.toml"
    new.write_text("[train]\nepochs = 2\n\n[train.loss]\nlovasz = 0.0\ndepth = 0.5\n")
    old = tmp_path / "old.toml"
    old.write_text("epochs = 2\nw_lovasz = 0.0\nw_depth = 0.5\n")
    a, b = load_config(new), load_config(old)
    assert a == b and (a.loss.lovasz, a.loss.depth, a.loss.focal) == (0.0, 0.5, 1.0)
    again = tmp_path / "again.toml"
    again.write_text(config_to_toml(a))
    assert "[train.loss]" in again.read_text() and load_config(again) == a
    flat_saved = {k: v for k, v in a.to_dict().items() if k != "loss"} | {f"w_{k}": v for k, v in
                                                                          dataclasses.asdict(a.loss).items()}
    assert incompatible_fields(flat_saved, a) == []  # a checkpoint written before the table resumes
    assert incompatible_fields(flat_saved, replace(a, loss=replace(a.loss, dice=2.0))) == ["loss.dice"]
    with pytest.raises(ConfigError, match="unknown \\[loss\\] key"):
        load_config(None, {"loss": {"lovaz": 0.0}})
    with pytest.raises(ConfigError, match="given twice"):
        load_config(None, {"loss": {"lovasz": 0.0}, "w_lovasz": 1.0})


# -- a stuck collective ---------------------------------------------------------------------------------
_HANG = textwrap.dedent("""
    import os, sys, time
    from fastocc import dist as D
    info = D.setup("cpu", timeout_s=3)
    if info.rank == 1:
        time.sleep(3600)  # never joins the collective (the test kills it)
        sys.exit(0)
    t0 = time.time()
    try:
        with D.collective_errors(info):
            D.barrier(info)
    except D.CollectiveError as exc:
        print("ERR", round(time.time() - t0), exc)
    os._exit(0)
""")


def test_a_stuck_collective_fails_with_one_line(tmp_path: Path) -> None:
    port = str(free_port())
    procs = [subprocess.Popen([sys.executable, "-c", _HANG], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env={**os.environ, "RANK": str(r), "WORLD_SIZE": "2", "LOCAL_RANK": str(r),
                                              "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": port})
             for r in range(2)]
    out, err = procs[0].communicate(timeout=120)
    procs[1].kill()
    procs[1].wait()
    lines = [ln for ln in out.splitlines() if ln.startswith("ERR")]
    assert len(lines) == 1, out + err
    seconds, msg = int(lines[0].split()[1]), lines[0]
    assert seconds >= 2, msg  # it waited for the 3 s timeout (how much longer is load, not behaviour)
    assert "rank 0: a collective operation with the other processes failed" in msg and "--resume" in msg


# -- the loader counts its own batches ------------------------------------------------------------------
@pytest.mark.parametrize("sequential", [False, True])
@pytest.mark.parametrize("workers", [0, 2])
def test_loader_reports_its_batches_and_takes_a_limit(synth_store: Path, sequential: bool, workers: int) -> None:
    sample = SampleConfig(image=ImageAugConfig(height=32, width=64), bev=BevAugConfig())
    for limit, batch in ((0, 1), (4, 2), (5, 2)):
        cfg = LoaderConfig(store=synth_store, batch_size=batch, sequential=sequential, sample=sample, seed=3,
                           limit_samples=limit)
        loader = make_loader(cfg, num_workers=workers)
        loader.dataset.set_epoch(1)
        got = [b.sample_index.tolist() for b in loader]
        assert loader_batches(loader) == len(got)
        seen = sorted(i for b in got for i in b)
        assert seen == open_store(synth_store).split_indices(None)[: limit or None].tolist()


def test_split_indices_is_one_definition(synth_store: Path) -> None:
    reader = open_store(synth_store)
    names = list(reader.attrs["splits"])
    split = reader.small("sample/split")
    for name in names:
        assert reader.split_indices(name).tolist() == np.flatnonzero(split == names.index(name)).tolist()
        assert reader.split_indices(name, labelled=False).tolist() == []  # the synthetic world is labelled
    assert len(reader.split_indices(None, labelled=True)) == len(split)
    with pytest.raises(OccDataError, match=r"split 'nope' is not in store .*unknown split"):
        reader.split_indices("nope")


def test_temporal_queue_state_round_trip() -> None:
    from fastocc.model.inputs import synthetic_inputs

    cfg = preset("nano", input_hw=(64, 176), num_history=2)
    model = FastOcc(cfg).eval()
    assert model.temporal.queue_state() is None
    with torch.no_grad():
        model(synthetic_inputs(1, cfg.input_hw, cfg.num_cams, seed=1))
        saved = model.temporal.queue_state()
        nxt = synthetic_inputs(1, cfg.input_hw, cfg.num_cams, seed=2)
        ref = model(nxt).voxel_logits
        model.clear_caches()
        model.temporal.load_queue_state(saved)
        again = model(nxt).voxel_logits
    assert torch.equal(ref, again)
    model.temporal.load_queue_state(None)
    assert model.temporal.queue_state() is None


# -- small things ---------------------------------------------------------------------------------------
def test_epoch_line_labels_raw_and_ema_figures() -> None:
    """Was: "val mIoU 0.31%" per epoch vs "best val mIoU 0.30%" at the end, raw vs EMA, unlabelled."""
    assert _val_text({"miou": 0.0031, "ema_miou": 0.003}) == ", val mIoU raw 0.31% / EMA 0.30%"
    assert _val_text({"miou": 0.0031}) == ", val mIoU raw 0.31%"


def test_predictor_checks_poses_and_names_the_default_rig() -> None:
    model = FastOcc(preset("nano", num_history=1))
    with pytest.warns(UserWarning, match="no rig given, using the default synthetic nuScenes-like rig"):
        pred = Predictor.from_model(model)
    images = [np.zeros((900, 1600, 3), np.uint8)] * 6
    scaled = np.eye(4)
    scaled[:3, :3] *= 2
    mirrored = np.diag([1.0, -1.0, 1.0, 1.0])
    bad_row = np.eye(4)
    bad_row[3, 0] = 0.5
    for pose, what in ((scaled, "not orthonormal"), (np.zeros((4, 4)), "last row"), (mirrored, "det = -1"),
                       (bad_row, "last row"), (np.full((4, 4), np.nan), "NaN"), (np.eye(3), "shape")):
        with pytest.raises(DeployError, match=what):
            pred(images, pose)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Predictor.from_model(model, synthetic_rig())  # a rig given: no warning


def test_broken_pipe_exits_quietly(synth_store: Path) -> None:
    """Was: `occdata info ... | head` printed "Error: Broken pipe" and exited 1."""
    proc = subprocess.Popen([sys.executable, "-m", "cli.occdata_cli", "info", "--store", str(synth_store)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert err == ""


def test_lock_names_this_host(tmp_path: Path) -> None:
    from fastocc.train.runlock import RunLock

    with RunLock(tmp_path):
        text = (tmp_path / ".lock").read_text().split()
    assert text == [str(os.getpid()), socket.gethostname()]
