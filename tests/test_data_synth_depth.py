"""On a synthetic store, loader depth targets under random augmentation agree with the exact
rendered depth maps (depth/<sample_data_token>.npy) resampled through the same matrix A."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr

from fastocc.data import ImageAugConfig, LoaderConfig, SampleConfig, StoreDataset
from occdata.store.build import BuildConfig, build_store
from occdata.store.layout import token_str

STRIDE = 16
H, W = 96, 176  # multiples of the stride; the synthetic source images are 400x225


@pytest.fixture(scope="module")
def synth_store(synth_root: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth_store") / "s.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=synth_root / "gts", progress=False))
    return out


def _agreement(synth_root: Path, synth_store: Path, train: bool, corrupt_A: bool = False) -> tuple[float, int]:
    """Fraction of depth targets lying within the rendered depths of their 16x16 patch."""
    cfg = LoaderConfig(store=synth_store, seed=3,
                       sample=SampleConfig(image=ImageAugConfig(height=H, width=W, train=train)))
    cam_tokens = zarr.open_group(str(synth_store), mode="r")["cam/token"][:]
    n_targets, matched = 0, 0
    for batch in StoreDataset(cfg):
        i = int(batch.sample_index[0])
        for c in range(6):
            gt = np.load(synth_root / "depth" / f"{token_str(cam_tokens[i, c])}.npy", allow_pickle=False)
            A = batch.img_aug[0, c].numpy().astype(np.float64)
            if corrupt_A:  # negative control: a horizontal flip the targets did not get
                A = np.array([[-1.0, 0, W - 1], [0, 1, 0], [0, 0, 1]]) @ A
            # Rendered depth resampled into the augmented image by the same A (nearest: no blending
            # across depth edges); sky and outside-the-source pixels are 0 and ignored.
            warped = cv2.warpPerspective(gt, A, (W, H), flags=cv2.INTER_NEAREST, borderValue=0)
            target = batch.depth_target[0, c].numpy()
            for py, px in zip(*np.nonzero(target), strict=True):
                patch = warped[py * STRIDE:(py + 1) * STRIDE, px * STRIDE:(px + 1) * STRIDE]
                surface = patch[patch > 0]
                d = float(target[py, px])
                # Nearest resampling moves a pixel by up to ~1 source pixel; on the ground that is a
                # few % of the depth at 400x225, hence the depth-relative margin.
                margin = 0.05 + 0.03 * d
                n_targets += 1
                matched += bool(surface.size) and surface.min() - margin <= d <= surface.max() + margin
    return matched / max(n_targets, 1), n_targets


@pytest.mark.parametrize("train", [True, False])
def test_depth_targets_match_rendered_depth_under_augmentation(synth_root, synth_store, train: bool) -> None:
    frac, n = _agreement(synth_root, synth_store, train)
    assert n > 200
    assert frac > 0.95, (frac, n)  # measured 0.98 (train) and 0.98 (test mode)


def test_depth_agreement_detects_wrong_geometry(synth_root, synth_store) -> None:
    frac, _ = _agreement(synth_root, synth_store, train=True, corrupt_A=True)
    assert frac < 0.8, frac  # measured 0.43: the check above can fail
