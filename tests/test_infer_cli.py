"""`fastocc predict` / `fastocc eval`: Occ3D-layout files equal to the in-memory predictions, pictures,
the round trip into `occdata eval`, and one clear error line for each bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cli.fastocc_cli import main
from fastocc.checkpoint import save_checkpoint
from fastocc.infer import PredictConfig, predict_split
from fastocc.model import FastOcc, preset
from occdata.constants import CLASS_COLORS, FREE_LABEL
from occdata.store.reader import open_store


@pytest.fixture(scope="module")
def nano_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A randomly initialised nano checkpoint (no trained weights needed to test the plumbing)."""
    torch.manual_seed(0)
    cfg = preset("nano")
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "nano.pt", cfg, FastOcc(cfg).state_dict())


@pytest.fixture(scope="module")
def predicted(synth_store: Path, nano_ckpt: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pred") / "out"
    res = CliRunner().invoke(main, ["predict", "--checkpoint", str(nano_ckpt), "--store", str(synth_store),
                                    "--out", str(out), "--png", "2", "--batch-size", "2", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "wrote 3 predictions" in res.output and "2 pictures" in res.output
    return out


def _val(store: Path) -> list[int]:
    r = open_store(store)
    return [int(i) for i in np.flatnonzero(r.small("sample/split") == list(r.attrs["splits"]).index("val"))]


def test_predict_files_equal_in_memory(synth_store: Path, nano_ckpt: Path, predicted: Path) -> None:
    r = open_store(synth_store)
    scenes = r.attrs["scenes"]
    files = sorted(p for p in predicted.rglob("*") if p.is_file() and p.suffix == ".npz")
    expect = {predicted / scenes[int(r.small("sample/scene_index")[i])]["name"] / r.token(i) / "labels.npz": i
              for i in _val(synth_store)}
    assert files == sorted(expect)
    assert not [p for p in predicted.rglob("*.tmp")]  # atomic writes leave no temporaries
    cfg = preset("nano")
    torch.manual_seed(0)
    model = FastOcc(cfg)
    direct = {}
    for batch, probs in predict_split(model, cfg, PredictConfig(store=synth_store, split="val", batch_size=2)):
        for b in range(len(batch)):
            direct[int(batch.sample_index[b])] = probs[b].argmax(0).to(torch.uint8).numpy()
    for path, i in expect.items():
        with np.load(path, allow_pickle=False) as z:
            assert list(z.keys()) == ["semantics"]
            sem = z["semantics"]
        assert sem.dtype == np.uint8 and sem.shape == (200, 200, 16)
        np.testing.assert_array_equal(sem, direct[i])


def test_pictures(synth_store: Path, predicted: Path) -> None:
    """N pictures, 1600 wide; the truth's 3D panel shows the colours of the classes its grid has."""
    pics = sorted((predicted / "pictures").glob("*.png"))
    assert len(pics) == 2
    r = open_store(synth_store)
    tokens = {r.token(i): i for i in _val(synth_store)}
    for p in pics:
        img = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
        assert img.shape[1] == 1600 and img.shape[0] > 1700
        token = p.stem.split("_")[-1]
        gt = r.sample_arrays(tokens[token], ("labels/semantics",))["labels/semantics"]
        truth_3d = img[630:1230, 800:]  # below the title and the two camera rows, right half
        # Classes with a large top surface (ground, roofs) must appear in their exact colour.
        counts = np.bincount(gt.ravel(), minlength=18)
        for c in range(FREE_LABEL):
            n = int(np.all(truth_3d == np.array(CLASS_COLORS[c], dtype=np.uint8), axis=-1).sum())
            if counts[c] > 3000:
                assert n > 0, (c, counts[c])
            if counts[c] == 0 and c not in (0,):  # class 0 is black, as are text pixels
                assert n == 0, c


def test_round_trip_into_occdata_eval(synth_store: Path, nano_ckpt: Path, predicted: Path) -> None:
    from cli.occdata_cli import main as occdata_main

    res = CliRunner().invoke(occdata_main, ["eval", "--pred", str(predicted), "--store", str(synth_store), "--json",
                                             "--no-progress"])
    assert res.exit_code == 0, res.output
    from_files = json.loads(res.output)
    res = CliRunner().invoke(main, ["eval", "--checkpoint", str(nano_ckpt), "--store", str(synth_store), "--json",
                                    "--no-progress"])
    assert res.exit_code == 0, res.output
    in_memory = json.loads(res.output)
    assert in_memory["n_samples"] == 3 and in_memory["frames_per_s"] > 0
    assert in_memory["miou"] > 0 and in_memory["geo_iou"] > 0  # a random network still hits some voxels
    for key in ("miou", "rayiou", "rayiou_at", "geo_iou", "per_class"):
        assert in_memory[key] == from_files[key], key


def _one_line_error(args: list[str], *needles: str) -> None:
    res = CliRunner().invoke(main, args)
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1 and lines[0].startswith("Error: "), res.output
    assert "Traceback" not in res.output
    for n in needles:
        assert n in lines[0], (n, lines[0])


@pytest.mark.parametrize("command", ["predict", "eval"])
def test_bad_inputs(command: str, synth_store: Path, nano_ckpt: Path, tmp_path: Path) -> None:
    extra = ["--out", str(tmp_path / "o")] if command == "predict" else []
    base = [command, "--store", str(synth_store), "--no-progress", *extra]
    _one_line_error([*base, "--checkpoint", str(tmp_path / "missing.pt")], "no such checkpoint")
    bare = tmp_path / "bare.pt"
    torch.save(FastOcc(preset("nano")).state_dict(), bare)
    _one_line_error([*base, "--checkpoint", str(bare)], "not a fastocc checkpoint", "bare state dict")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    _one_line_error([*base, "--checkpoint", str(junk)], "not a readable fastocc checkpoint")
    _one_line_error([*base, "--checkpoint", str(nano_ckpt), "--split", "nope"], "unknown split", "val")
    _one_line_error([command, "--store", str(tmp_path / "nostore.zarr"), "--checkpoint", str(nano_ckpt), *extra],
                    "store not found")
    if not torch.cuda.is_available():
        _one_line_error([*base, "--checkpoint", str(nano_ckpt), "--device", "cuda"], "no CUDA device")
    if command == "predict":
        f = tmp_path / "afile"
        f.write_text("x")
        _one_line_error([command, "--store", str(synth_store), "--checkpoint", str(nano_ckpt), "--out", str(f)],
                        "not a folder")


def test_picture_indices_spread_over_split() -> None:
    from fastocc.infer.write import picture_indices

    idx = np.arange(10) + 5
    assert picture_indices(idx, 3) == [5, 9, 14]  # positions 0, round(4.5) = 4, 9: first, middle, last
    assert picture_indices(idx, 1) == [5]
    assert picture_indices(idx, 50) == list(range(5, 15))
    assert picture_indices(idx, 0) == [] and picture_indices(np.array([], dtype=np.int64), 2) == []
