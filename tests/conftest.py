"""Shared fixtures: paths to the real nuScenes/Occ3D data in ../shared (never copied here)."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
REAL_NUSCENES = SHARED_DATA / "nuscenes-real"
REAL_OCC3D_LABEL = SHARED_DATA / "occ3d-label" / "29796060110c4163b07f06eff4af0753" / "labels.npz"


def pytest_configure(config: pytest.Config) -> None:
    # A run started in the background by a non-interactive shell (`bash scripts/test.sh &`) inherits SIGINT
    # ignored, and so would every process the tests start: the Ctrl-C tests need the usual disposition.
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


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
