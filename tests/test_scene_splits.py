"""Scene splits for trees outside nuScenes' official lists: a split file, the `auto` rule, and the one
line when a split is empty or a split file is broken. On the REAL Lyft tree (one scene, no official split)
and the real scene-0916 (official mini_val)."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.errors import OccDataError
from occdata.nuscenes import load_nuscenes
from occdata.nuscenes.splits import SplitChoice, auto_split
from occdata.store.reader import open_store

LYFT_SCENE = "host-a101-lidar0-1241893239199111666-1241893264098084346"


def test_auto_puts_one_scene_in_five_in_val_by_a_hash_of_its_name() -> None:
    assert zlib.crc32(LYFT_SCENE.encode()) % 5 == 2  # worked out by hand: train
    assert auto_split(LYFT_SCENE) == "train"
    names = [f"log-{i:04d}" for i in range(1000)]
    val = [n for n in names if auto_split(n) == "val"]
    assert 150 < len(val) < 250  # about one in five
    assert all(zlib.crc32(n.encode()) % 5 == 0 for n in val)


def test_a_tree_without_official_splits_trains_by_default(real_lyft_root: Path) -> None:
    assert load_nuscenes(real_lyft_root).scenes[0].split == "train"
    unassigned = load_nuscenes(real_lyft_root, splits=SplitChoice(unlisted="unassigned"))
    assert unassigned.scenes[0].split == "unassigned"


def test_a_split_file_decides_before_the_official_lists(real_lyft_root: Path, real_seq_root: Path,
                                                         tmp_path: Path) -> None:
    f = tmp_path / "splits.json"
    f.write_text(json.dumps({"val": [LYFT_SCENE, "scene-0916"], "test": ["not-in-the-tree"]}))
    lyft = load_nuscenes(real_lyft_root, splits=SplitChoice(f))
    assert lyft.scenes[0].split == "val"
    assert any("2 of its scenes are not in the tables (first: 'not-in-the-tree')" in w for w in lyft.warnings)
    seq = load_nuscenes(real_seq_root)
    assert seq.scenes[0].split == "mini_val"  # official, without a split file
    f.write_text(json.dumps({"train": ["scene-0916"]}))
    assert load_nuscenes(real_seq_root, splits=SplitChoice(f)).scenes[0].split == "train"


@pytest.mark.parametrize(("content", "message"), [
    ("{", "not JSON"),
    ("[]", 'expected {"train"'),
    ('{"train": "scene-1"}', "split 'train' is not a list of scene names"),
    ('{"tr ain": ["scene-1"]}', "'tr ain' is not a split name"),
    ('{"train": ["a"], "val": ["a"]}', "scene 'a' is in 'train' and 'val'"),
])
def test_a_broken_split_file_is_one_line(tmp_path: Path, content: str, message: str) -> None:
    f = tmp_path / "s.json"
    f.write_text(content)
    with pytest.raises(OccDataError, match="split file") as err:
        SplitChoice(f).table()
    assert message in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(OccDataError, match="cannot read"):
        SplitChoice(tmp_path / "absent.json").table()
    with pytest.raises(OccDataError, match="not a split name"):
        SplitChoice(unlisted="no/slash")


def test_build_records_the_split_rule_and_train_names_an_empty_split(real_lyft_root: Path, tmp_path: Path) -> None:
    f = tmp_path / "splits.json"
    f.write_text(json.dumps({"val": [LYFT_SCENE]}))
    out = tmp_path / "lyft.zarr"
    res = CliRunner().invoke(main, ["build", "--root", str(real_lyft_root), "--out", str(out), "--no-progress",
                                    "--split-file", str(f), "--cameras", "CAM_FRONT", "--lidars", "LIDAR_TOP"])
    assert res.exit_code == 0, res.output
    reader = open_store(out)
    assert reader.attrs["splits"] == ["val"]
    assert reader.attrs["build_identity"]["scene_splits"] == {"file": str(f.resolve()), "unlisted": "auto"}
    from fastocc.train.state import class_counts

    with pytest.raises(OccDataError, match=r"split 'train' is not in store .*the store has \['val'\]; a store's "
                                           r"splits are set when it is built: occdata build --split-file"):
        class_counts(out, "train", use_camera_mask=True)
    res = CliRunner().invoke(main, ["build", "--root", str(real_lyft_root), "--out", str(out), "--no-progress",
                                    "--cameras", "CAM_FRONT", "--lidars", "LIDAR_TOP", "--resume"])
    assert res.exit_code != 0 and "--split-file" in res.output  # a resume must split the same way


def test_training_names_a_missing_validation_split_at_start(real_lyft_root: Path, tmp_path: Path) -> None:
    from fastocc.train.setup import check_val_split

    out = tmp_path / "lyft.zarr"
    res = CliRunner().invoke(main, ["build", "--root", str(real_lyft_root), "--out", str(out), "--no-progress",
                                    "--cameras", "CAM_FRONT", "--lidars", "LIDAR_TOP"])
    assert res.exit_code == 0, res.output
    with pytest.raises(OccDataError, match=r"validation split 'val' has no labelled samples .*\{'train': 0\}.*"
                                           r"val_every = 0 to train without validation"):
        check_val_split(str(out), "val")
