"""Issue 47 items 3-5: defaults that work on a one-split store, errors that name the real problem, one
meaning per name (--device, --json units, --index, "no boxes", --help defaults, counts in words).

The commands run as a newcomer types them: `CliRunner` in a folder (the default store data.zarr), and the
slow end-to-end test in fresh processes (`python -m cli.*` is this checkout's `occdata` / `fastocc`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import click
import pytest
from click._utils import UNSET
from click.testing import CliRunner, Result

from cli.fastocc_cli import main as fastocc_main
from cli.occdata_cli import main as occdata_main
from cli.options import ShownDefault, _field_default
from occdata.errors import OccDataError
from occdata.store.splits import default_split
from occdata.text import plural

REPO = Path(__file__).resolve().parents[1]
GROUPS = (occdata_main, fastocc_main)


# -- a one-scene world: it has only the split `train` ----------------------------------------------------
@pytest.fixture(scope="module")
def one_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding `world/` (1 scene x 2 keyframes, 400x225) and its store `data.zarr`."""
    from occdata.store.build import BuildConfig, build_store
    from occdata.synth import SynthConfig, synthesize

    folder = tmp_path_factory.mktemp("one_scene")
    world = synthesize(SynthConfig(out=folder / "world", scenes=1, samples=2, seed=3, width=400, height=225,
                                   progress=False))
    build_store(BuildConfig(root=world, out=folder / "data.zarr", gts=world / "gts", progress=False))
    return folder


def _run(group: click.Group, *args: str) -> Result:
    return CliRunner().invoke(group, list(args))


def test_default_split_is_val_else_the_only_split() -> None:
    assert default_split(["train", "val", "test"], "s.zarr").split == "val"
    assert default_split(["train", "val"], "s.zarr").note is None
    chosen = default_split(["train"], "s.zarr")
    assert chosen.split == "train"
    assert chosen.note == "store s.zarr has no 'val' split: using its only split, 'train' (--split chooses another)"
    with pytest.raises(OccDataError, match=r"no 'val' split and several others \(mini_train, mini_val\): give --split"):
        default_split(["mini_train", "mini_val"], "s.zarr")
    with pytest.raises(OccDataError, match="has no splits"):
        default_split([], "s.zarr")


def test_store_commands_default_to_the_only_split(one_scene: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Was: "split 'val' is not in store". The labels of the world itself serve as predictions."""
    monkeypatch.chdir(one_scene)
    note = "note: store data.zarr has no 'val' split: using its only split, 'train' (--split chooses another)"
    r = _run(occdata_main, "baseline", "--json")
    assert r.exit_code == 0, r.output
    assert r.stderr.splitlines() == [note]
    got = json.loads(r.stdout)
    assert (got["split"], got["samples"], got["unit"]) == ("train", 2, "percent")
    assert 0 < got["miou_camera_mask"] <= 100
    r = _run(occdata_main, "eval", "--pred", "world/gts", "--no-rayiou", "--no-progress", "--json")
    assert r.exit_code == 0, r.output
    assert r.stderr.splitlines() == [note]
    got = json.loads(r.stdout)
    assert (got["split"], got["n_samples"], got["miou"]) == ("train", 2, 100.0)  # the truth scores 100%
    r = _run(occdata_main, "eval", "--pred", "world/gts", "--no-rayiou", "--no-progress", "--split", "val")
    assert r.exit_code == 1 and "split 'val' is not in store" in r.stderr  # a named split is never replaced


@pytest.mark.slow
def test_one_scene_world_runs_build_train_eval_predict_with_defaults(tmp_path: Path) -> None:
    """The commands exactly as typed, in fresh processes (about 2 minutes on a loaded 2-core VM). Was:
    `fastocc train` stopped with "validation split 'val' has no labelled samples"."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}

    def run(tool: str, *args: str) -> subprocess.CompletedProcess[str]:
        r = subprocess.run([sys.executable, "-m", f"cli.{tool}_cli", *args], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, (args, r.stdout + r.stderr)
        assert "Traceback" not in r.stderr
        return r

    run("occdata", "synth", "--out", "world", "--scenes", "1", "--samples", "2", "--width", "400", "--height", "225",
        "--no-progress")
    run("occdata", "build", "--root", "world", "--no-progress")
    r = run("fastocc", "train", "--store", "data.zarr", "--epochs", "1", "--no-progress")
    assert ("validation: store data.zarr has no 'val' split: using its only split, 'train' (val_split in a "
            "--config TOML chooses another)") in r.stdout.splitlines()
    assert r.stdout.splitlines()[-1].startswith("done: 1 epoch, 2 steps; best val mIoU"), r.stdout
    ckpt = "runs/fastocc/best.pt"
    assert (tmp_path / ckpt).is_file()
    note = "note: store data.zarr has no 'val' split: using its only split, 'train' (--split chooses another)"
    r = run("fastocc", "eval", "--checkpoint", ckpt, "--no-progress")
    assert note in r.stderr.splitlines() and "train: 2 samples, mIoU" in r.stdout
    r = run("fastocc", "predict", "--checkpoint", ckpt, "--out", "pred", "--no-progress")
    assert note in r.stderr.splitlines() and "wrote 2 predictions" in r.stdout
    r = run("occdata", "eval", "--pred", "pred", "--no-progress")
    assert note in r.stderr.splitlines() and "train: 2 samples, mIoU" in r.stdout


# -- errors: one line naming the real problem ------------------------------------------------------------
def _error_line(group: click.Group, *args: str) -> str:
    """The one line a refused command prints (stdout empty, no traceback)."""
    r = _run(group, *args)
    assert r.exit_code == 1, r.output
    assert r.stdout == "" and "Traceback" not in r.stderr, r.output
    (line,) = r.stderr.splitlines()
    assert line.startswith("Error: ")
    return line.removeprefix("Error: ")


def test_scan_root_that_is_a_file_or_an_empty_folder(tmp_path: Path) -> None:
    afile = tmp_path / "afile.txt"
    afile.write_text("hello")
    assert _error_line(occdata_main, "scan", "--root", str(afile)) == (
        f"dataset root {afile} is a file, not a folder: --root names the folder that holds the version folder "
        "(v1.0-trainval/, ...), samples/ and sweeps/")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _error_line(occdata_main, "scan", "--root", str(empty)) == (
        f"{empty} holds no nuScenes tables: no folder in it has a scene.json (expected e.g. "
        f"{empty / 'v1.0-trainval' / 'scene.json'})")
    assert _error_line(occdata_main, "scan", "--root", str(tmp_path / "nope")) == (
        f"dataset root not found: {tmp_path / 'nope'}")


def test_scan_root_that_is_the_version_folder(synth_root: Path) -> None:
    assert _error_line(occdata_main, "scan", "--root", str(synth_root / "v1.0-mini")) == (
        f"--root {synth_root / 'v1.0-mini'} is a version folder itself (it holds scene.json): give its parent, "
        f"{synth_root}")


def test_build_root_not_found_is_the_only_line(tmp_path: Path) -> None:
    """Was: "labels: none (no --gts, ...)" on stdout before the error."""
    assert _error_line(occdata_main, "build", "--root", "/nonexistent", "--out", str(tmp_path / "s.zarr")) == (
        "dataset root not found: /nonexistent")


def test_build_out_in_the_way(synth_root: Path, tmp_path: Path) -> None:
    """Was: "store exists ... pass --resume", and --resume failed again. Said before the tables are read
    and before the store's lock is taken, so nothing is left beside the file."""
    afile = tmp_path / "afile.txt"
    afile.write_text("hello")
    base = ["build", "--root", str(synth_root), "--no-progress"]
    want = f"--out {afile} is a file, not a store folder: choose another --out (or remove the file)"
    assert _error_line(occdata_main, *base, "--out", str(afile)) == want
    assert _error_line(occdata_main, *base, "--out", str(afile), "--resume") == want
    assert afile.read_text() == "hello" and sorted(p.name for p in tmp_path.iterdir()) == ["afile.txt"]
    full = tmp_path / "full"
    full.mkdir()
    for name in ("a", "b", "c", "d"):
        (full / name).write_text("")
    assert _error_line(occdata_main, *base, "--out", str(full)) == (
        f"--out {full} is a folder that holds no zarr store (4 entries: a, b, c, ...): choose another --out, or an "
        "empty or new folder")


def test_build_into_an_empty_folder(synth_root: Path, tmp_path: Path) -> None:
    from occdata.store.reader import open_store

    empty = tmp_path / "store"
    empty.mkdir()
    r = _run(occdata_main, "build", "--root", str(synth_root), "--out", str(empty), "--no-progress")
    assert r.exit_code == 0, r.output
    assert f"{empty}: 6/6 samples done, 0 errors" in r.stdout
    assert open_store(empty).n_samples == 6


@pytest.mark.parametrize("command", ["eval", "predict"])
def test_a_missing_checkpoint_is_said_before_the_store(command: str, tmp_path: Path) -> None:
    """Was: the split (of a store that is not there either) first."""
    args = [command, "--checkpoint", "/nonexistent.pt", "--store", str(tmp_path / "none.zarr")]
    args += ["--out", str(tmp_path / "pred")] if command == "predict" else []
    assert _error_line(fastocc_main, *args) == "/nonexistent.pt: no such checkpoint file"
    assert _error_line(fastocc_main, *args[:2], str(tmp_path), *args[3:]) == (
        f"{tmp_path}: is a folder, not a checkpoint file (e.g. {tmp_path / 'best.pt'})")


# -- one meaning per name --------------------------------------------------------------------------------
def _options(group: click.Group, name: str) -> list[click.Option]:
    return [p for p in group.commands[name].params if isinstance(p, click.Option) and not p.hidden]


COMMANDS = [(g, name) for g in GROUPS for name in g.commands]


@pytest.mark.parametrize(("group", "name"), COMMANDS, ids=[f"{g.name}-{n}" for g, n in COMMANDS])
def test_help_shows_every_default(group: click.Group, name: str) -> None:
    """Every option whose value is not "off" or "not given" when omitted shows it in --help."""
    cmd = group.commands[name]
    ctx = click.Context(cmd, info_name=name, parent=click.Context(group, info_name=group.name,
                                                                    show_default=True))
    for p in _options(group, name):
        if p.is_flag and not p.secondary_opts:  # --tta, --resume: off unless given
            continue
        record = p.get_help_record(ctx)
        assert record is not None, p.name
        described = isinstance(p, ShownDefault) and (
            p.default_text or (p.config_field and _field_default(p.config_field) is not None))
        if described or p.default not in (None, UNSET, ()):
            assert "[default: " in record[1], (name, p.opts, record[1])
        assert "[default: True]" not in record[1] and "[default: (" not in record[1], (name, p.opts, record[1])


def test_train_help_shows_the_config_defaults() -> None:
    from fastocc.train.config import TrainConfig

    r = _run(fastocc_main, "train", "--help")
    text = " ".join(r.output.split())  # help lines wrap anywhere
    cfg = TrainConfig()
    for opt, shown in (("--epochs", cfg.epochs), ("--batch-size", cfg.batch_size), ("--lr", f"{cfg.lr:g}"),
                       ("--workers", cfg.workers), ("--preset", cfg.preset), ("--device", "auto")):
        after = text.split(f" {opt} ", 1)[1]
        assert after[after.index("[default: "):].startswith(f"[default: {shown}, or the --config file's"), opt


def test_device_is_auto_everywhere() -> None:
    found = [(g.name, n, p) for g, n in COMMANDS for p in _options(g, n) if p.name == "device"]
    assert {n for _, n, _ in found} >= {"bench", "train", "eval", "predict"}
    for group_name, name, p in found:
        assert list(p.type.choices) == ["auto", "cpu", "cuda"], (group_name, name)
        assert p.default == "auto" or (name == "train" and p.default is None), (group_name, name)


def test_device_auto_reaches_the_run_as_the_device_there(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import torch

    import fastocc.bench

    seen: list[str] = []

    def stand_in(cfg: object) -> dict[str, object]:
        seen.append(cfg.device)
        raise SystemExit(0)

    monkeypatch.setattr(fastocc.bench, "run_benchmark", stand_in)
    assert _run(fastocc_main, "bench").exit_code == 0
    assert seen == ["cuda" if torch.cuda.is_available() else "cpu"]


def test_index_defaults_to_0_everywhere() -> None:
    found = [(n, p) for g, n in COMMANDS for p in _options(g, n) if "--index" in p.opts]
    assert {n for n, _ in found} == {"dump", "check-projection", "show-batch"}
    assert all(p.default == 0 and not p.required for _, p in found), [(n, p.default, p.required) for n, p in found]


def test_json_unit_is_named_in_help() -> None:
    for group, name in ((occdata_main, "eval"), (occdata_main, "baseline"), (occdata_main, "visibility-check"),
                        (fastocc_main, "eval")):
        (opt,) = [p for p in _options(group, name) if p.name == "as_json"]
        assert "in percent" in opt.help, (name, opt.help)


def _labels_options(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, *extra: str) -> object:
    import occdata.labels

    seen: list[object] = []

    def stand_in(cfg: object) -> None:
        seen.append(cfg.options)
        raise SystemExit(0)

    monkeypatch.setattr(occdata.labels, "generate_labels", stand_in)
    r = _run(occdata_main, "labels", "--root", str(tmp_path), "--out", str(tmp_path / "o"), *extra)
    assert r.exit_code == 0 and len(seen) == 1, r.output
    return seen[0]


def test_one_way_to_say_no_boxes(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """`--boxes none` withholds the boxes (and carves), `--no-carve` turns carving off: the naive control
    is the two together. `--no-boxes` (which meant that) is refused with the new spelling."""
    o = _labels_options(monkeypatch, tmp_path)
    assert (o.use_boxes, o.carve) == (True, None)
    o = _labels_options(monkeypatch, tmp_path, "--boxes", "none")
    assert (o.use_boxes, o.carve) == (False, True)
    o = _labels_options(monkeypatch, tmp_path, "--boxes", "none", "--no-carve")
    assert (o.use_boxes, o.carve) == (False, False)
    assert _error_line(occdata_main, "labels", "--root", str(tmp_path), "--out", str(tmp_path / "o"),
                       "--no-boxes") == "--no-boxes is gone: use --boxes none --no-carve (the naive control; " \
                                        "--boxes none alone carves)"
    assert "--no-boxes" not in _run(occdata_main, "labels", "--help").output


def test_counts_in_words() -> None:
    assert [plural(n, "scene") for n in (0, 1, 2)] == ["0 scenes", "1 scene", "2 scenes"]
    assert plural(1, "process", "processes") == "1 process" and plural(3, "process", "processes") == "3 processes"


def test_one_scene_world_says_one_scene(tmp_path: Path) -> None:
    r = _run(occdata_main, "synth", "--out", str(tmp_path / "w"), "--scenes", "1", "--samples", "1", "--width", "64",
             "--height", "36", "--no-progress")
    assert r.exit_code == 0 and f"wrote 1 scene x 1 sample to {tmp_path / 'w'}" in r.stdout, r.output
    r = _run(occdata_main, "scan", "--root", str(tmp_path / "w"))
    assert r.exit_code == 0 and ": 1 scene, 1 sample" in r.stdout.splitlines()[0], r.output
    assert "1 scenes" not in r.output and "1 samples" not in r.output
    shutil.rmtree(tmp_path / "w")
