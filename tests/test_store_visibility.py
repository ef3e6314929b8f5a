"""`occdata visibility` on synthetic stores: reproduces the synth masks, fills a label-only store."""

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
from occdata.store.commands.visibility import compute_visibility


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


@pytest.fixture(scope="module")
def synth_store(synth_root: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("vis") / "s.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=synth_root / "gts", progress=False))
    return out


def test_recompute_reproduces_synth_masks_per_class(synth_store: Path, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    shutil.copytree(synth_store, store)
    code, text = _cli("visibility", "--store", str(store), "--recompute", "--no-progress")
    assert code == 0, text
    # Within the shipped mask_lidar the camera test is the synth's own: same masks up to float32 calibration.
    iou_all, iou_occ, iou_free = map(float, re.search(
        r"mask_camera: IoU all ([0-9.]+), occupied ([0-9.]+), free ([0-9.]+)", text).groups())
    assert min(iou_all, iou_occ, iou_free) >= 0.99, text
    assert re.search(r"^  car +\d+ +[0-9.]+% +[0-9.]+% +[01]\.\d{3}", text, re.M), text  # a per-class row
    g = zarr.open_group(str(store), mode="r")
    assert g["visibility/present"][:].all()
    cam, shipped = g["visibility/camera"][:], g["labels/mask_camera"][:]
    assert cam.any() and (cam == shipped).mean() > 0.999
    # LiDAR rays rebuilt from the stored (in-image) keyframe points: a subset of the synth's rays (it also
    # aggregates neighbouring sweeps), so up to float32 rounding a subset of its mask_lidar.
    lidar, mask_lidar = g["visibility/lidar"][:].astype(bool), g["labels/mask_lidar"][:].astype(bool)
    outside = (lidar & ~mask_lidar).sum() / lidar.sum()
    assert lidar.sum() > 10_000 and outside < 0.01, outside
    code, text = _cli("verify", "--store", str(store), "--no-progress")
    assert code == 0, text  # checksums were updated with the new arrays


def test_label_only_store_gets_both_masks(synth_root: Path, tmp_path: Path) -> None:
    """Labels with semantics only (custom data): `occdata visibility` fills both masks, Occ3D-like."""
    gts = tmp_path / "gts"
    for f in (synth_root / "gts").glob("*/*/labels.npz"):
        out = gts / f.relative_to(synth_root / "gts")
        out.parent.mkdir(parents=True)
        with np.load(f) as z:
            np.savez_compressed(out, semantics=z["semantics"])
    store = tmp_path / "labels_only.zarr"
    build_store(BuildConfig(root=synth_root, out=store, gts=gts, progress=False))
    g = zarr.open_group(str(store), mode="r")
    assert g["labels/present"][:].all() and not g["labels/mask_camera"][:].any()
    code, text = _cli("visibility", "--store", str(store), "--no-progress")
    assert code == 0 and "computed for 6 samples" in text, text
    sem = g["labels/semantics"][:]
    cam, lidar = g["visibility/camera"][:].astype(bool), g["visibility/lidar"][:].astype(bool)
    assert not (cam & ~lidar).any()
    frac = {c: cam[sem == c].mean() for c in (4, 11, 17)}  # car, driveable surface, free
    assert frac[4] > 0.5 and frac[11] > 0.2 and frac[17] < 0.3, frac
    np.testing.assert_array_equal(cam[sem == 17], lidar[sem == 17])  # free: visible where observed


def test_default_mode_only_fills_missing_masks(synth_store: Path, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    shutil.copytree(synth_store, store)
    assert compute_visibility(store, progress=False).computed == 0  # every sample ships a mask
    g = zarr.open_group(str(store), mode="r+")
    g["labels/mask_camera"][1] = 0  # custom data without a camera mask (checksum kept consistent: readers check it)
    col = list(g.attrs["checksum_arrays"]).index("labels/mask_camera")
    g["status/checksum"][1, col] = zlib.crc32(np.zeros(g["labels/mask_camera"].shape[1:], np.uint8).tobytes())
    report = compute_visibility(store, progress=False)
    assert report.computed == 1 and report.compared == 0
    assert g["visibility/present"][:].tolist() == [False, True] + [False] * (g["visibility/present"].shape[0] - 2)


def test_unlabelled_store_is_a_clear_error(real_nuscenes_root: Path, tmp_path: Path) -> None:
    store = tmp_path / "real.zarr"
    build_store(BuildConfig(root=real_nuscenes_root, out=store, progress=False))
    code, text = _cli("visibility", "--store", str(store), "--no-progress")
    assert code != 0 and "no labelled samples" in text and "Traceback" not in text
    assert np.asarray(zarr.open_group(str(store), mode="r")["visibility/present"][:]).sum() == 0
