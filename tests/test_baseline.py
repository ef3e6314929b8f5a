"""`occdata baseline`: the per-voxel most frequent training label, scored like any prediction."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.store.reader import open_store


def test_baseline_scores_as_occdata_eval_scores_the_same_prediction(synth_store, tmp_path):
    reader = open_store(synth_store)
    names = list(reader.attrs["splits"])
    split = reader.small("sample/split")
    sem = reader.array("labels/semantics")
    train = np.flatnonzero(split == names.index("train"))
    # the majority label per voxel, counted here with np.unique (ties: the lower label)
    stack = np.stack([np.asarray(sem[int(i)]) for i in train]).reshape(len(train), -1)
    majority = np.array([np.unique(col, return_counts=True) for col in stack.T[::997]], dtype=object)
    pred_dir = tmp_path / "pred"
    pred_dir.mkdir()
    counts = np.zeros((stack.shape[1], 18), np.int64)
    np.add.at(counts, (np.arange(stack.shape[1])[None, :].repeat(len(train), 0), stack), 1)
    pred = counts.argmax(1).astype(np.uint8)
    for (vals, cnt), p in zip(majority, pred[::997], strict=True):  # spot-check the argmax against np.unique
        assert p == vals[np.argmax(cnt)]
    tokens = reader.small("sample/token")
    for i in np.flatnonzero(split == names.index("val")):
        token = bytes(tokens[i]).rstrip(b"\0").decode()
        np.savez_compressed(pred_dir / f"{token}.npz", semantics=pred.reshape(200, 200, 16))

    runner = CliRunner()
    got = runner.invoke(main, ["baseline", "--store", str(synth_store), "--json"])
    assert got.exit_code == 0, got.output
    base = json.loads(got.output)
    ref = runner.invoke(main, ["eval", "--pred", str(pred_dir), "--store", str(synth_store), "--no-rayiou", "--json",
                               "--no-progress"])
    assert ref.exit_code == 0, ref.output
    ref_json = json.loads(ref.output)
    assert base["train_samples"] == len(train) and base["samples"] == ref_json["n_samples"]
    assert base["unit"] == ref_json["unit"] == "percent" and (base["train_split"], base["split"]) == ("train", "val")
    assert 0 < base["miou_camera_mask"] < 100
    assert abs(base["miou_camera_mask"] - ref_json["miou"]) < 2e-4  # both percent to 4 decimals
    assert "val_samples" not in base


def test_baseline_without_a_val_split_is_one_line(synth_store):
    got = CliRunner().invoke(main, ["baseline", "--store", str(synth_store), "--split", "nope"])
    assert got.exit_code != 0
    assert "split 'nope' is not in store" in got.output
