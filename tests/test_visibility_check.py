"""`occdata visibility-check` on the real Occ3D label with the real fixture's camera rig (docs/visibility.md).

The figures are the ones reported in docs/visibility.md and docs/benchmarks-labels.md: the test fails if the
definition regresses (or silently changes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO


def _check(label: Path, root: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli.occdata_cli", "visibility-check", "--label", str(label),
                           "--root", str(root), *extra], cwd=REPO, capture_output=True, text=True, timeout=600)


def test_real_label_agreement(real_occ3d_label: Path, real_nuscenes_root: Path) -> None:
    r = _check(real_occ3d_label, real_nuscenes_root, "--json")
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["unit"] == "percent"  # as every --json (cli.options.JSON_UNITS)
    assert got["iou_all"] == pytest.approx(87.44, abs=0.1)
    assert got["iou_occupied"] == pytest.approx(77.62, abs=0.1)
    assert got["iou_free"] == pytest.approx(100.0, abs=1e-4)
    assert got["precision"] == pytest.approx(92.43, abs=0.1) and got["recall"] == pytest.approx(94.19, abs=0.1)
    pct = got["visible"]
    # The label's own visible shares (docs/design.md#visibility-masks) come back beside ours.
    assert pct["car"]["label"] == pytest.approx(90.6, abs=0.1)
    assert pct["free"]["label"] == pytest.approx(3.4, abs=0.1)
    # Ground classes and free space: visible exactly where LiDAR-observed, as in the label.
    for name in ("driveable_surface", "sidewalk", "terrain", "free"):
        assert pct[name]["ours"] == pytest.approx(pct[name]["label"], abs=1e-3)
    for name, ours in (("car", 76.6), ("manmade", 59.6), ("vegetation", 47.2)):
        assert pct[name]["ours"] == pytest.approx(ours, abs=0.2)
    # Strict occlusion (the paper's literal reading, one object voxel deep) finds far less.
    strict = json.loads(_check(real_occ3d_label, real_nuscenes_root, "--json", "--max-occluders", "0").stdout)
    assert strict["iou_occupied"] == pytest.approx(49.65, abs=0.1) and strict["precision"] > 99


def test_text_output_and_bad_input(real_occ3d_label: Path, real_nuscenes_root: Path, tmp_path: Path) -> None:
    r = _check(real_occ3d_label, real_nuscenes_root)
    assert r.returncode == 0 and "IoU with the label's mask_camera: all 0.874" in r.stdout, r.stdout + r.stderr
    assert "driveable_surface" in r.stdout
    bad = tmp_path / "labels.npz"
    bad.write_bytes(b"not a zip")
    r = _check(bad, real_nuscenes_root)
    assert r.returncode == 1 and r.stderr.startswith("Error:") and "Traceback" not in r.stderr
    r = _check(real_occ3d_label, real_nuscenes_root, "--sample", "nope")
    assert r.returncode == 1 and "sample 'nope' not found" in r.stderr
