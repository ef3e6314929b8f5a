"""Dataset roots reached through symlinks (as on clusters): record paths keep the root as named.

Uses the REAL scene-0916 tree in ../shared/data through symlinks made in a temp folder (nothing is
copied). Independent truth: the paths are checked against `root / row["filename"]` from the JSON
rows, and the files against the file system.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from conftest import REAL_SEQ, missing_fixture

from occdata.errors import OccDataError
from occdata.nuscenes import load_nuscenes, validate_sample
from occdata.nuscenes.reader import confined_path, dataset_root


@pytest.fixture(scope="module")
def seq_real() -> Path:
    if not (REAL_SEQ / "v1.0-mini" / "sample_data.json").is_file():
        missing_fixture("real nuScenes scene", REAL_SEQ)
    return REAL_SEQ.resolve()


@pytest.fixture(scope="module")
def filenames(seq_real: Path) -> dict[str, str]:
    rows = json.loads((seq_real / "v1.0-mini" / "sample_data.json").read_text())
    return {r["token"]: r["filename"] for r in rows}


def _check_paths(root: Path, filenames: dict[str, str]) -> None:
    ds = load_nuscenes(root, check_files=True, sweeps=True)
    assert ds.root == root and len(ds.samples) == 41
    n_sweeps = 0
    for s in ds.samples:
        validate_sample(s)
        for rec in (*s.cameras, s.lidar):
            assert rec.path == root / filenames[rec.token] and rec.path.is_file()
        for sw in s.sweeps:
            assert sw.path == root / filenames[sw.token]  # files not shipped: only the path
            n_sweeps += 1
    assert n_sweeps == 358


def test_symlinked_root_keeps_its_name(seq_real: Path, filenames: dict[str, str], tmp_path: Path) -> None:
    link = tmp_path / "nuscenes"
    link.symlink_to(seq_real, target_is_directory=True)
    _check_paths(link, filenames)


def test_root_under_a_symlinked_folder(seq_real: Path, filenames: dict[str, str], tmp_path: Path) -> None:
    (tmp_path / "data").symlink_to(seq_real.parent, target_is_directory=True)
    _check_paths(tmp_path / "data" / seq_real.name, filenames)


def test_relative_symlinked_root(
    seq_real: Path, filenames: dict[str, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "nusc").symlink_to(seq_real, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    assert dataset_root("nusc") == tmp_path / "nusc"
    assert dataset_root("./nusc/") == tmp_path / "nusc"
    _check_paths(tmp_path / "nusc", filenames)


def test_dotdot_after_a_symlink_is_resolved(seq_real: Path, tmp_path: Path) -> None:
    # <tmp>/cams -> <seq>/samples; "<tmp>/cams/.." is <seq> for the OS, <tmp> for a lexical rule.
    (tmp_path / "cams").symlink_to(seq_real / "samples", target_is_directory=True)
    root = tmp_path / "cams" / ".."
    assert dataset_root(root) == seq_real
    ds = load_nuscenes(root, check_files=True)
    assert len(ds.samples) == 41 and all(s.lidar.path.is_file() for s in ds.samples)


def test_confinement_is_lexical_under_a_symlinked_root(seq_real: Path, tmp_path: Path) -> None:
    link = tmp_path / "nuscenes"
    link.symlink_to(seq_real, target_is_directory=True)
    assert confined_path(link, "samples/LIDAR_TOP/x.bin", "row") == link / "samples" / "LIDAR_TOP" / "x.bin"
    assert confined_path(link, "samples/../samples/x", "row") == link / "samples" / "x"
    for bad in ("../nuscenes-real/x", "/etc/passwd", "samples/../../x", "."):
        with pytest.raises(OccDataError, match="points outside") as info:
            confined_path(link, bad, "sample_data 'abc' filename")
        assert "\n" not in str(info.value) and str(link) in str(info.value)
    # A symlink placed inside the tree is followed as usual (not refused, not resolved).
    inner = tmp_path / "tree"
    inner.mkdir()
    (inner / "samples").symlink_to(seq_real / "samples", target_is_directory=True)
    path = confined_path(inner, "samples/CAM_FRONT", "row")
    assert path == inner / "samples" / "CAM_FRONT" and path.is_dir() and os.path.realpath(path) != str(path)
