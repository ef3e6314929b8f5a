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
    assert got["iou_all"] == pytest.approx(0.8744, abs=1e-3)
    assert got["iou_occupied"] == pytest.approx(0.7762, abs=1e-3)
    assert got["iou_free"] == pytest.approx(1.0, abs=1e-6)
    assert got["precision"] == pytest.approx(0.9243, abs=1e-3) and got["recall"] == pytest.approx(0.9419, abs=1e-3)
    frac = got["visible_fraction"]
    # The label's own fractions (DESIGN §5.3) come back beside ours.
    assert frac["car"]["label"] == pytest.approx(0.906, abs=1e-3)
    assert frac["free"]["label"] == pytest.approx(0.034, abs=1e-3)
    # Ground classes and free space: visible exactly where LiDAR-observed, as in the label.
    for name in ("driveable_surface", "sidewalk", "terrain", "free"):
        assert frac[name]["ours"] == pytest.approx(frac[name]["label"], abs=1e-9)
    for name, ours in (("car", 0.766), ("manmade", 0.596), ("vegetation", 0.472)):
        assert frac[name]["ours"] == pytest.approx(ours, abs=2e-3)
    # Strict occlusion (the paper's literal reading, one object voxel deep) finds far less.
    strict = json.loads(_check(real_occ3d_label, real_nuscenes_root, "--json", "--max-occluders", "0").stdout)
    assert strict["iou_occupied"] == pytest.approx(0.4965, abs=1e-3) and strict["precision"] > 0.99


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
