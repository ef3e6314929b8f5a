"""Shared fixtures: paths to the real nuScenes/Occ3D data in ../shared (never copied here)."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import NoReturn

import pytest

REPO = Path(__file__).resolve().parents[1]
# The real-data fixtures sit beside the clone (../shared/data); OCCDATA_SHARED_DATA points elsewhere.
SHARED_DATA = Path(os.environ.get("OCCDATA_SHARED_DATA") or REPO.parent / "shared" / "data")
REAL_NUSCENES = SHARED_DATA / "nuscenes-real"
REAL_SEQ = SHARED_DATA / "nuscenes-real-seq"
REAL_LYFT = SHARED_DATA / "lyft-real"
REAL_OCC3D_LABEL_DIR = SHARED_DATA / "occ3d-label"
REAL_OCC3D_LABEL = REAL_OCC3D_LABEL_DIR / "29796060110c4163b07f06eff4af0753" / "labels.npz"


SHARED_HOW = "the real-data fixtures go in ../shared/data beside the clone, or set OCCDATA_SHARED_DATA"


def missing_fixture(what: str, path: Path, how: str = SHARED_HOW) -> NoReturn:
    """A test fixture from outside the repository is absent: fail under CI (`CI=true`, where it must be
    there), else skip (a fresh clone has no ../shared). One line naming what is missing and where it goes."""
    msg = f"{what} missing at {path} ({how})"
    if os.environ.get("CI", "").lower() in ("true", "1"):
        pytest.fail(msg)
    pytest.skip(msg)


def pytest_configure(config: pytest.Config) -> None:
    # A run started in the background by a non-interactive shell (`bash scripts/test.sh &`) inherits SIGINT
    # ignored, and so would every process the tests start: the Ctrl-C tests need the usual disposition.
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def real_nuscenes_root() -> Path:
    if not REAL_NUSCENES.is_dir():
        missing_fixture("real nuScenes keyframe", REAL_NUSCENES)
    return REAL_NUSCENES


@pytest.fixture(scope="session")
def real_seq_root() -> Path:
    """The real scene-0916 sequence (tables with annotations and sweeps)."""
    for table in ("sample_data", "sample_annotation"):
        if not (REAL_SEQ / "v1.0-mini" / f"{table}.json").is_file():
            missing_fixture("real nuScenes scene", REAL_SEQ)
    return REAL_SEQ


@pytest.fixture(scope="session")
def real_lyft_root() -> Path:
    """The 16 real Lyft Level 5 keyframes (7 cameras, 3 LiDARs, tables in train_data/, no boxes)."""
    if not (REAL_LYFT / "train_data" / "sample_data.json").is_file():
        missing_fixture("real Lyft keyframes", REAL_LYFT)
    return REAL_LYFT


@pytest.fixture(scope="session")
def real_occ3d_label() -> Path:
    if not REAL_OCC3D_LABEL.is_file():
        missing_fixture("real Occ3D label", REAL_OCC3D_LABEL)
    return REAL_OCC3D_LABEL


@pytest.fixture(scope="session")
def real_occ3d_label_dir(real_occ3d_label: Path) -> Path:
    """The Occ3D example folder (flat layout: <sample token>/labels.npz)."""
    return REAL_OCC3D_LABEL_DIR


# --- synthetic world (occdata synth): one small world per test session ----------------------------
SYNTH_SMALL = {"scenes": 2, "samples": 3, "seed": 7, "width": 400, "height": 225}


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-scene x 3-sample synthetic nuScenes tree at 400x225 (built once per session)."""
    from occdata.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("synth") / "world"
    return synthesize(SynthConfig(out=out, progress=False, **SYNTH_SMALL))


@pytest.fixture(scope="session")
def synth_store(synth_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small synthetic world built into a store once per session (treat as read-only)."""
    from occdata.store.build import BuildConfig, build_store

    out = tmp_path_factory.mktemp("store") / "data.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=synth_root / "gts", progress=False))
    return out
