"""`occdata visibility --lidar-sweeps N`: mask_lidar of a label-only store from aggregated sweeps."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.constants import FREE_LABEL
from occdata.store.build import BuildConfig, build_store


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


@pytest.fixture(scope="module")
def label_only(synth_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A store whose labels carry semantics only (custom data), so visibility computes both masks."""
    tmp = tmp_path_factory.mktemp("labels_only")
    for f in (synth_root / "gts").glob("*/*/labels.npz"):
        out = tmp / "gts" / f.relative_to(synth_root / "gts")
        out.parent.mkdir(parents=True)
        with np.load(f) as z:
            np.savez_compressed(out, semantics=z["semantics"])
    store = tmp / "s.zarr"
    build_store(BuildConfig(root=synth_root, out=store, gts=tmp / "gts", progress=False))
    return store


def _lidar_mask(store: Path, tmp_path: Path, name: str, *args: str) -> tuple[np.ndarray, str]:
    import shutil

    copy = tmp_path / name
    shutil.copytree(store, copy)
    code, text = _cli("visibility", "--store", str(copy), "--no-progress", *args)
    assert code == 0, text
    g = zarr.open_group(str(copy), mode="r")
    assert g["visibility/present"][:].all()
    return g["visibility/lidar"][:].astype(bool), text


def test_aggregated_sweeps_observe_more_free_space(label_only: Path, tmp_path: Path) -> None:
    sem = zarr.open_group(str(label_only), mode="r")["labels/semantics"][:]
    free = sem == FREE_LABEL
    stored, _ = _lidar_mask(label_only, tmp_path, "a.zarr")
    m0, t0 = _lidar_mask(label_only, tmp_path, "b.zarr", "--lidar-sweeps", "0")
    m4, _ = _lidar_mask(label_only, tmp_path, "c.zarr", "--lidar-sweeps", "4")
    m9, t9 = _lidar_mask(label_only, tmp_path, "d.zarr", "--lidar-sweeps", "9")
    # The stored depth targets are the keyframe points inside some image: a subset of the whole sweep
    # (up to float32 rounding of the stored u, v, depth at voxel faces).
    assert (stored & ~m0).sum() < 0.001 * stored.sum()
    # More sweeps, more rays: each mask contains the previous one, and observes more free space.
    assert not (m0 & ~m4).any() and not (m4 & ~m9).any()
    cover = [m[free].mean() for m in (stored, m0, m4, m9)]
    print(f"\nfree voxels observed: stored points {cover[0]:.4f}, N=0 {cover[1]:.4f}, N=4 {cover[2]:.4f}, "
          f"N=9 {cover[3]:.4f}")
    assert cover[0] < cover[1] < cover[2] < cover[3]
    assert f"{100 * cover[3]:.2f}% of free voxels observed" in t9, t9
    # Samples without previous sweeps (the first keyframe of each scene) gain nothing.
    for i in (0, 3):
        np.testing.assert_array_equal(m0[i], m9[i])


def test_missing_sweep_files_one_line(label_only: Path, synth_root: Path, tmp_path: Path) -> None:
    root = tmp_path / "tree"
    root.mkdir()
    for name in ("v1.0-mini", "samples", "gts", "maps", "depth"):
        os.symlink(synth_root / name, root / name)
    code, text = _cli("visibility", "--store", str(label_only), "--no-progress", "--lidar-sweeps", "2",
                      "--root", str(root))
    # The keyframe files are needed too: 6 keyframes + 8 sweeps.
    assert code == 1 and "--lidar-sweeps 2: missing sweep file" in text and "6 of the 14 sweep files" in text, text
    assert len(text.strip().splitlines()) == 1
    assert not zarr.open_group(str(label_only), mode="r")["visibility/present"][:].any()  # nothing written
