"""Non-keyframe LIDAR_TOP sweeps in the reader, on the REAL scene-0916 tables (../shared/data)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_SEQ, missing_fixture

from occdata.errors import OccDataError
from occdata.nuscenes import load_nuscenes


@pytest.fixture(scope="module")
def seq_root() -> Path:
    if not (REAL_SEQ / "v1.0-mini" / "sample_data.json").is_file():
        missing_fixture("real nuScenes scene", REAL_SEQ)
    return REAL_SEQ


def _tables(root: Path) -> dict[str, list[dict]]:
    return {t: json.loads((root / "v1.0-mini" / f"{t}.json").read_text())
            for t in ("sample", "sample_data", "calibrated_sensor", "sensor", "ego_pose", "scene")}


def _expected_between(tables: dict[str, list[dict]]) -> list[list[int]]:
    """Per keyframe (scene order), the timestamps of the non-keyframe LIDAR_TOP rows strictly between
    the previous keyframe's LIDAR_TOP timestamp and its own, newest first: from timestamps alone, not
    from the prev/next links the reader follows."""
    channel = {s["token"]: s["channel"] for s in tables["sensor"]}
    lidar_cs = {c["token"] for c in tables["calibrated_sensor"] if channel[c["sensor_token"]] == "LIDAR_TOP"}
    lidar = [sd for sd in tables["sample_data"] if sd["calibrated_sensor_token"] in lidar_cs]
    key_ts = {sd["sample_token"]: sd["timestamp"] for sd in lidar if sd["is_key_frame"]}
    sweep_ts = sorted(sd["timestamp"] for sd in lidar if not sd["is_key_frame"])
    by_token = {s["token"]: s for s in tables["sample"]}
    (scene,) = tables["scene"]
    order, tok = [], scene["first_sample_token"]
    while tok:
        order.append(tok)
        tok = by_token[tok]["next"]
    out, lo = [], -np.inf
    for tok in order:
        hi = key_ts[tok]
        out.append(sorted((t for t in sweep_ts if lo < t < hi), reverse=True))
        lo = hi
    return out


def test_real_scene_sweep_counts_match_the_tables(seq_root: Path) -> None:
    tables = _tables(seq_root)
    expected = _expected_between(tables)
    ds = load_nuscenes(seq_root, sweeps=True)
    assert len(ds.samples) == 41 == len(expected)
    got = [[sw.timestamp for sw in s.sweeps] for s in ds.samples]
    assert got == expected
    counts = [len(e) for e in expected[1:]]
    assert sum(counts) + len(expected[0]) == 358 and min(counts) == 7 and max(counts) == 9  # 20 Hz vs 2 Hz
    # Each sweep carries its own ego pose (from ego_pose.json) and the LIDAR_TOP calibration.
    poses = {p["token"]: p for p in tables["ego_pose"]}
    sd_rows = {sd["token"]: sd for sd in tables["sample_data"]}
    for s in ds.samples[1:4]:
        for sw in s.sweeps:
            row = sd_rows[sw.token]
            assert not row["is_key_frame"] and sw.path == seq_root / row["filename"]
            assert row["filename"].startswith("sweeps/LIDAR_TOP/")
            np.testing.assert_allclose(sw.T_global_from_ego[:3, 3], poses[row["ego_pose_token"]]["translation"])
            np.testing.assert_allclose(sw.T_ego_from_lidar, s.lidar.T_ego_from_lidar)


def test_lidar_history_crosses_keyframes_nearest_first(seq_root: Path) -> None:
    ds = load_nuscenes(seq_root, sweeps=True)
    hist = ds.lidar_history(3, 12)  # sample 3 has 7 sweeps, then sample 2's keyframe, then its sweeps
    assert len(hist) == 12
    ts = [h.timestamp for h in hist]
    assert ts == sorted(ts, reverse=True) and ts[0] < ds.samples[3].lidar.timestamp
    assert hist[7].token == ds.samples[2].lidar.token
    assert ds.lidar_history(0, 9) == ()  # the scene's first keyframe: start of the chain
    assert len(ds.lidar_history(1, 40)) == 10  # 9 sweeps + keyframe 0, then the chain ends
    with pytest.raises(ValueError):
        load_nuscenes(seq_root).lidar_history(3, 2)
    assert load_nuscenes(seq_root).samples[3].sweeps == ()  # keyframes only by default


def _edited_copy(seq_root: Path, tmp_path: Path, edit) -> Path:
    root = tmp_path / "tree"
    (root / "v1.0-mini").mkdir(parents=True)
    for f in (seq_root / "v1.0-mini").iterdir():
        shutil.copyfile(f, root / "v1.0-mini" / f.name)
    sd_path = root / "v1.0-mini" / "sample_data.json"
    rows = json.loads(sd_path.read_text())
    edit(rows, {r["token"]: r for r in rows})
    sd_path.write_text(json.dumps(rows))
    return root


def _a_sweep(rows: list[dict], lidar_sweep_prefix: str = "sweeps/LIDAR_TOP/") -> dict:
    sweeps = sorted((r for r in rows if r["filename"].startswith(lidar_sweep_prefix)), key=lambda r: r["timestamp"])
    return sweeps[40]


@pytest.mark.parametrize("case, message", [
    # the links are checked for every row first (every command reads them alike): a dangling or one-sided
    # link is named there, before the LiDAR chain is followed
    ("dangling", "refers to sample_data 'ffffffffffffffffffffffffffffffff', not in sample_data.json"),
    ("next_disagrees", "but that row's prev is"),
    ("skips_to_keyframe", "but that row's prev is"),
    ("cut", "before the previous keyframe's LIDAR_TOP"),
    ("other_scene", "a row of another scene"),
])
def test_broken_sweep_chains_are_one_line_errors(seq_root: Path, tmp_path: Path, case: str, message: str) -> None:
    def edit(rows: list[dict], by_tok: dict[str, dict]) -> None:
        sw = _a_sweep(rows)
        if case == "dangling":
            sw["prev"] = "f" * 32
        elif case == "next_disagrees":
            by_tok[sw["prev"]]["next"] = by_tok[sw["next"]]["token"]
        elif case == "skips_to_keyframe":  # a link to the keyframe two keyframes back
            keys = sorted((r for r in rows if r["is_key_frame"] and "LIDAR_TOP" in r["filename"]),
                          key=lambda r: r["timestamp"])
            older = [k for k in keys if k["timestamp"] < sw["timestamp"]][-2]
            sw["prev"] = older["token"]
            older["next"] = sw["token"]
        elif case == "cut":
            by_tok[sw["prev"]]["next"] = ""
            sw["prev"] = ""
        elif case == "other_scene":
            sw["sample_token"] = "0" * 32  # a sample of another scene, added below
    root = _edited_copy(seq_root, tmp_path, edit)
    if case == "other_scene":
        samples = json.loads((root / "v1.0-mini" / "sample.json").read_text())
        samples.append({"token": "0" * 32, "timestamp": 0, "prev": "", "next": "", "scene_token": "1" * 32})
        (root / "v1.0-mini" / "sample.json").write_text(json.dumps(samples))
        scenes = json.loads((root / "v1.0-mini" / "scene.json").read_text())
        scenes.append({**scenes[0], "token": "1" * 32, "name": "other", "nbr_samples": 1,
                       "first_sample_token": "0" * 32, "last_sample_token": "0" * 32})
        (root / "v1.0-mini" / "scene.json").write_text(json.dumps(scenes))
        # The other scene's only sample has no sample_data: read keyframes only, that alone fails
        # differently, so check the sweep chain error comes first through the first scene.
    with pytest.raises(OccDataError) as info:
        load_nuscenes(root, sweeps=True)
    msg = str(info.value)
    assert "\n" not in msg and message in msg, msg
    if case != "other_scene":
        assert len(load_nuscenes(root).samples) == 41  # keyframes alone still read


def test_scan_reports_sweeps_per_keyframe(seq_root: Path) -> None:
    from click.testing import CliRunner

    from cli.occdata_cli import main

    res = CliRunner().invoke(main, ["scan", "--root", str(seq_root), "--json"])
    assert res.exit_code == 0, res.output
    sw = json.loads(res.output)["sweeps"]
    assert sw == {"total": 358, "per_keyframe_min": 7, "per_keyframe_mean": round(358 / 40, 3),
                  "per_keyframe_max": 9, "files_present": 0}
    res = CliRunner().invoke(main, ["scan", "--root", str(seq_root)])
    assert "LIDAR_TOP sweeps between keyframes: 8.95 per keyframe (min 7, max 9), 358 in all; 0 of their files" \
        in res.output
