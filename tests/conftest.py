"""Shared fixtures: paths to the real nuScenes/Occ3D data in ../shared (never copied here)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
REAL_NUSCENES = SHARED_DATA / "nuscenes-real"
REAL_OCC3D_LABEL = SHARED_DATA / "occ3d-label" / "29796060110c4163b07f06eff4af0753" / "labels.npz"


@pytest.fixture(scope="session")
def real_nuscenes_root() -> Path:
    if not REAL_NUSCENES.is_dir():
        pytest.fail(f"real nuScenes fixture missing at {REAL_NUSCENES} (expected ../shared/data)")
    return REAL_NUSCENES


@pytest.fixture(scope="session")
def real_occ3d_label() -> Path:
    if not REAL_OCC3D_LABEL.is_file():
        pytest.fail(f"real Occ3D label missing at {REAL_OCC3D_LABEL}")
    return REAL_OCC3D_LABEL
