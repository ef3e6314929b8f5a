"""`occdata visibility` on a synthetic store reproduces the synthetic world's own mask_camera."""

from __future__ import annotations

import re
import shutil
import zlib
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.store.build import BuildConfig, build_store
from occdata.store.visibility_cmd import compute_visibility


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


@pytest.fixture(scope="module")
def synth_store(synth_root: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("vis") / "s.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=synth_root / "gts", progress=False))
    return out


def test_recompute_reproduces_synth_mask_camera(synth_store: Path, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    shutil.copytree(synth_store, store)
    code, text = _cli("visibility", "--store", str(store), "--recompute", "--no-progress")
    assert code == 0, text
    mean, low = map(float, re.search(r"mean ([0-9.]+), min ([0-9.]+)", text).groups())
    assert low >= 0.99 and mean >= 0.99, text
    g = zarr.open_group(str(store), mode="r")
    assert g["visibility/present"][:].all()
    cam, shipped = g["visibility/camera"][:], g["labels/mask_camera"][:]
    assert cam.any() and (cam == shipped).mean() > 0.99
    # LiDAR rays rebuilt from the stored (in-image) depth points: a subset of the world's rays, so
    # (up to float32 rounding of u, v, depth) a subset of the synthetic mask_lidar.
    lidar, mask_lidar = g["visibility/lidar"][:].astype(bool), g["labels/mask_lidar"][:].astype(bool)
    outside = (lidar & ~mask_lidar).sum() / lidar.sum()
    assert lidar.sum() > 10_000 and outside < 0.01, outside
    code, text = _cli("verify", "--store", str(store), "--no-progress")
    assert code == 0, text  # checksums were updated with the new arrays


def test_default_mode_only_fills_missing_masks(synth_store: Path, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    shutil.copytree(synth_store, store)
    assert compute_visibility(store, progress=False).computed == 0  # every sample ships a mask
    g = zarr.open_group(str(store), mode="r+")
    g["labels/mask_camera"][1] = 0  # custom data without a camera mask (checksum kept consistent: readers check it)
    col = list(g.attrs["checksum_arrays"]).index("labels/mask_camera")
    g["status/checksum"][1, col] = zlib.crc32(np.zeros(g["labels/mask_camera"].shape[1:], np.uint8).tobytes())
    report = compute_visibility(store, progress=False)
    assert report.computed == 1 and report.agreement_iou == {}
    assert g["visibility/present"][:].tolist() == [False, True] + [False] * (g["visibility/present"].shape[0] - 2)


def test_unlabelled_store_is_a_clear_error(real_nuscenes_root: Path, tmp_path: Path) -> None:
    store = tmp_path / "real.zarr"
    build_store(BuildConfig(root=real_nuscenes_root, out=store, progress=False))
    code, text = _cli("visibility", "--store", str(store), "--no-progress")
    assert code != 0 and "no labelled samples" in text and "Traceback" not in text
    assert np.asarray(zarr.open_group(str(store), mode="r")["visibility/present"][:]).sum() == 0
