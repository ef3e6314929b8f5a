"""Bad rig inputs are one line each, other layouts read as their devkits read them: copies of the REAL Lyft
tables (sensor files linked, never copied) with one edit each, and a TIER IV-style `annotation/` + `data/`
layout made from the small synthetic world."""

from __future__ import annotations

import json
import math
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.nuscenes import load_nuscenes
from occdata.store.reader import open_store

Rows = list[dict]


def _lyft_copy(real_lyft_root: Path, tmp_path: Path) -> Path:
    root = tmp_path / "lyft"
    shutil.copytree(real_lyft_root / "train_data", root / "train_data")
    for folder in ("train_images", "train_lidar", "maps"):
        os.symlink(real_lyft_root / folder, root / folder)
    return root


def _edit(root: Path, table: str, fn: Callable[[Rows], None]) -> None:
    path = root / "train_data" / f"{table}.json"
    rows = json.loads(path.read_text())
    fn(rows)
    path.write_text(json.dumps(rows))


def _scan(root: Path) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["scan", "--root", str(root)])
    return res.exit_code, res.output


def _sensor_token(root: Path, channel: str) -> str:
    rows = json.loads((root / "train_data" / "sensor.json").read_text())
    return next(r["token"] for r in rows if r["channel"] == channel)


def _calib_of(root: Path, channel: str) -> str:
    tok = _sensor_token(root, channel)
    rows = json.loads((root / "train_data" / "calibrated_sensor.json").read_text())
    return next(r["token"] for r in rows if r["sensor_token"] == tok)


def test_a_channel_named_twice_is_one_line(real_lyft_root: Path, tmp_path: Path) -> None:
    root = _lyft_copy(real_lyft_root, tmp_path)
    _edit(root, "sensor", lambda rows: rows.append({**rows[0], "token": "f" * 64}))
    code, out = _scan(root)
    assert code == 1
    assert f"channel '{json.loads((root / 'train_data' / 'sensor.json').read_text())[0]['channel']}' is named by " \
           "two sensors" in out


def test_a_camera_without_intrinsics_is_one_line(real_lyft_root: Path, tmp_path: Path) -> None:
    root = _lyft_copy(real_lyft_root, tmp_path)
    cal = _calib_of(root, "CAM_FRONT_ZOOMED")
    _edit(root, "calibrated_sensor", lambda rows: next(r for r in rows if r["token"] == cal).pop("camera_intrinsic"))
    code, out = _scan(root)
    assert code == 1 and f"calibrated_sensor.json: row {cal!r} has no field 'camera_intrinsic'" in out


def test_a_lidar_without_calibration_is_one_line(real_lyft_root: Path, tmp_path: Path) -> None:
    root = _lyft_copy(real_lyft_root, tmp_path)
    cal = _calib_of(root, "LIDAR_FRONT_RIGHT")
    _edit(root, "calibrated_sensor", lambda rows: rows.remove(next(r for r in rows if r["token"] == cal)))
    code, out = _scan(root)
    assert code == 1
    assert f"refers to calibrated_sensor {cal!r}, not in calibrated_sensor.json" in out


def test_a_nan_image_size_names_its_row(real_lyft_root: Path, tmp_path: Path) -> None:
    """Lyft's LiDAR rows carry NaN sizes (not read: a LiDAR has none); a camera row's NaN is an error."""
    root = _lyft_copy(real_lyft_root, tmp_path)
    cam = {}

    def nan_width(rows: Rows) -> None:
        row = next(r for r in rows if "CAM_BACK" in r["filename"] or "cam" in r["filename"])
        row["width"] = math.nan
        cam["token"] = row["token"]

    _edit(root, "sample_data", nan_width)
    code, out = _scan(root)
    assert code == 1 and f"sample_data {cam['token']!r} width is not an integer (nan)" in out


def test_unused_sensors_are_named_with_their_reason(real_lyft_root: Path, tmp_path: Path) -> None:
    root = _lyft_copy(real_lyft_root, tmp_path)
    _edit(root, "sensor", lambda rows: rows.extend([
        {"token": "a" * 64, "channel": "RADAR_FRONT", "modality": "radar"},
        {"token": "b" * 64, "channel": "CAM_SPARE", "modality": "camera"}]))
    ds = load_nuscenes(root)
    assert ds.rig.left_out == ("CAM_SPARE (camera: no keyframe rows in sample_data.json)",
                               "RADAR_FRONT (radar: not a camera or LiDAR)")
    code, out = _scan(root)
    assert code == 0 and "left out: CAM_SPARE (camera: no keyframe rows in sample_data.json)" in out


def test_a_chosen_reference_lidar_defines_the_key_ego_frame(real_lyft_root: Path) -> None:
    ds = load_nuscenes(real_lyft_root, rig=None)
    from occdata.nuscenes.rig import RigChoice

    other = load_nuscenes(real_lyft_root, rig=RigChoice(reference_lidar="LIDAR_FRONT_LEFT"))
    assert other.rig.lidars == ("LIDAR_FRONT_LEFT", "LIDAR_FRONT_RIGHT", "LIDAR_TOP")  # the others by name
    a, b = ds.samples[3], other.samples[3]
    assert b.lidar.channel == "LIDAR_FRONT_LEFT" and b.timestamp == a.timestamp
    assert b.T_global_from_keyego is b.lidar.T_global_from_ego


def test_a_tier4_style_layout_reads_and_builds(synth_root: Path, tmp_path: Path) -> None:
    """T4 (TIER IV) keeps its tables in `annotation/` and its sensor files under `data/<CHANNEL>/`."""
    root = tmp_path / "t4"
    shutil.copytree(synth_root / "v1.0-mini", root / "annotation")
    rows = json.loads((root / "annotation" / "sample_data.json").read_text())
    for r in rows:
        src = synth_root / r["filename"]
        r["filename"] = "data/" + r["filename"].split("/", 1)[1]
        dst = root / r["filename"]
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_file():
            os.symlink(src, dst)
    (root / "annotation" / "sample_data.json").write_text(json.dumps(rows))
    for name in ("maps",):
        os.symlink(synth_root / name, root / name)
    code, out = _scan(root)
    assert code == 0, out
    assert "[annotation]" in out
    res = CliRunner().invoke(main, ["build", "--root", str(root), "--out", str(tmp_path / "t4.zarr"), "--no-progress"])
    assert res.exit_code == 0, res.output
    assert open_store(tmp_path / "t4.zarr").n_samples == len(load_nuscenes(synth_root).samples)


@pytest.mark.parametrize("option, value, message", [
    ("--cameras", "CAM_FRONT,CAM_FRONT", "--cameras names CAM_FRONT twice"),
    ("--lidars", "LIDAR_X", "--lidars: LIDAR_X is not a LiDAR with keyframe rows"),
    ("--reference-lidar", "LIDAR_X", "--reference-lidar LIDAR_X is not a LiDAR of the rig"),
])
def test_bad_rig_options_are_one_line(real_lyft_root: Path, option: str, value: str, message: str) -> None:
    res = CliRunner().invoke(main, ["scan", "--root", str(real_lyft_root), option, value])
    assert res.exit_code != 0 and message in res.output and "Traceback" not in res.output


def test_a_tree_without_log_json_reads_as_truckscenes_ships_it(real_lyft_root: Path, tmp_path: Path) -> None:
    """MAN TruckScenes has no log table (scene.log_token is ""): the location is then unknown, not an error."""
    root = _lyft_copy(real_lyft_root, tmp_path)
    (root / "train_data" / "log.json").unlink()
    _edit(root, "scene", lambda rows: rows[0].update(log_token=""))
    ds = load_nuscenes(root)
    assert ds.scenes[0].location == "" and ds.scenes[0].log_token == ""
    assert _scan(root)[0] == 0
