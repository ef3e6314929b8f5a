"""Broken nuScenes trees give one clear error line naming the file or token, and exit != 0."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.errors import OccDataError
from occdata.nuscenes import load_lidar_points


def _clone_tree(src: Path, dst: Path) -> Path:
    """Tables copied (so they can be broken), sensor files linked (never copied)."""
    shutil.copytree(src / "v1.0-mini", dst / "v1.0-mini")
    for f in (src / "samples").rglob("*"):
        if f.is_file():
            target = dst / f.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(f)
    return dst


def _scan(root: Path) -> tuple[int, str]:
    result = CliRunner().invoke(main, ["scan", "--root", str(root)])
    return result.exit_code, result.output


@pytest.fixture
def tree(real_nuscenes_root, tmp_path) -> Path:
    return _clone_tree(real_nuscenes_root, tmp_path / "ns")


def _assert_one_clear_line(code: int, output: str, *needles: str) -> None:
    assert code != 0
    lines = [ln for ln in output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), output
    assert "Traceback" not in output
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_clone_is_valid(tree) -> None:
    code, out = _scan(tree)
    assert code == 0, out
    assert "1 scene, 1 sample" in out


def test_missing_table(tree) -> None:
    (tree / "v1.0-mini" / "sample_data.json").unlink()
    _assert_one_clear_line(*_scan(tree), "missing table", "sample_data.json")


def test_missing_sensor_file(tree) -> None:
    victim = next((tree / "samples" / "CAM_BACK").iterdir())
    victim.unlink()
    _assert_one_clear_line(*_scan(tree), "missing sensor file", victim.name)


def test_dangling_token(tree) -> None:
    path = tree / "v1.0-mini" / "sample_data.json"
    rows = json.loads(path.read_text())
    rows[2]["ego_pose_token"] = "deadbeef" * 4
    path.write_text(json.dumps(rows))
    _assert_one_clear_line(*_scan(tree), "dangling token", "deadbeef" * 4, "ego_pose")


def test_dangling_scene_first_sample(tree) -> None:
    path = tree / "v1.0-mini" / "scene.json"
    rows = json.loads(path.read_text())
    rows[0]["first_sample_token"] = "f00d" * 8
    path.write_text(json.dumps(rows))
    _assert_one_clear_line(*_scan(tree), "dangling token", "f00d" * 8, "scene-0061")


@pytest.mark.parametrize("cut", [10, 200, -3])
def test_malformed_json(tree, cut: int) -> None:
    path = tree / "v1.0-mini" / "calibrated_sensor.json"
    text = path.read_text()
    path.write_text(text[:cut])
    _assert_one_clear_line(*_scan(tree), "malformed JSON", "calibrated_sensor.json")


def test_json_not_an_array(tree) -> None:
    (tree / "v1.0-mini" / "log.json").write_text('{"token": "x"}')
    _assert_one_clear_line(*_scan(tree), "malformed JSON", "log.json", "array")


def test_missing_field(tree) -> None:
    path = tree / "v1.0-mini" / "sample_data.json"
    rows = json.loads(path.read_text())
    del rows[0]["filename"]
    path.write_text(json.dumps(rows))
    _assert_one_clear_line(*_scan(tree), "sample_data.json", "filename")


def test_wrong_version_lists_present(tree) -> None:
    result = CliRunner().invoke(main, ["scan", "--root", str(tree), "--version", "v1.0-trainval"])
    _assert_one_clear_line(result.exit_code, result.output, "v1.0-trainval", "v1.0-mini")


@pytest.mark.parametrize("n_bytes", [0, 21, 99])
def test_truncated_lidar(tmp_path, n_bytes: int) -> None:
    path = tmp_path / "x.pcd.bin"
    path.write_bytes(b"\0" * n_bytes)
    with pytest.raises(OccDataError, match="multiple of 20"):
        load_lidar_points(path)
