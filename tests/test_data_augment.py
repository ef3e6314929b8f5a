"""Geometry under augmentation: images, depth targets, labels and the matrices A and M agree."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fastocc.data.augment import (
    BevAug,
    BevAugConfig,
    ImageAugConfig,
    apply_bev_aug,
    choose_reduce,
    sample_bev_aug,
    sample_image_aug,
)
from fastocc.data.sample import decode_augmented
from occdata.constants import GRID
from occdata.sensors.depth_targets import depth_target

# A plausible front camera: 1600x900, looking along key-ego +x from 1.5 m height.
K = np.array([[1266.0, 0, 816.0], [0, 1266.0, 491.0], [0, 0, 1]])
T_keyego_from_cam = np.eye(4)
T_keyego_from_cam[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # cam z -> ego x, cam x -> ego -y
T_keyego_from_cam[:3, 3] = [1.5, 0.2, 1.5]


def _project(P: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = P @ np.append(p, 1.0)
    return q[:2] / q[2]


def _blob_jpeg(u: float, v: float) -> np.ndarray:
    img = np.zeros((900, 1600, 3), np.uint8)
    cv2.circle(img, (round(u * 16), round(v * 16)), 6 * 16, (255, 255, 255), -1, cv2.LINE_AA, shift=4)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    return buf.ravel()


def _centroid(img: np.ndarray) -> np.ndarray:
    w = img[..., 0].astype(np.float64)
    w[w < 40] = 0
    ys, xs = np.indices(w.shape)
    return np.array([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("size", [(256, 704), (320, 800)])
def test_point_lands_where_the_augmented_image_shows_it(seed: int, size: tuple[int, int]) -> None:
    rng = np.random.default_rng(seed)
    cfg = ImageAugConfig(height=size[0], width=size[1], train=True)
    bev = sample_bev_aug(BevAugConfig(rot_deg=20.0, scale=(0.9, 1.1)), rng)
    M = bev.matrix
    hits = 0
    for _ in range(6):
        # A key-ego point in view, expressed in the AUGMENTED frame as the model sees it.
        p = np.array([rng.uniform(12, 30), rng.uniform(-6, 6), rng.uniform(0, 3)])
        p_aug = (M @ np.append(p, 1))[:3]
        u0 = _project(K @ np.linalg.inv(T_keyego_from_cam)[:3], p)
        aug = sample_image_aug(cfg, 1600, 900, rng)
        A = aug.matrix
        P = A @ K @ np.linalg.inv(T_keyego_from_cam)[:3] @ np.linalg.inv(M)
        expected = _project(P, p_aug)
        if not (10 < expected[0] < size[1] - 10 and 10 < expected[1] < size[0] - 10):
            continue
        out = decode_augmented(_blob_jpeg(*u0), A, aug.scale, 1600, 900, size[1], size[0])
        assert out is not None and out.shape == (size[0], size[1], 3)
        np.testing.assert_allclose(_centroid(out), expected, atol=0.35)
        # The depth target of the point sits in the patch containing that pixel.
        d = np.linalg.norm(p)  # any depth in range
        dt = depth_target(np.array([[*u0, d]], np.float32), A, size[0], size[1], 16, 1.0, 45.0)
        (py,), (px,) = np.nonzero(dt)
        assert (px, py) == (int(np.floor(expected[0] + 0.5)) // 16, int(np.floor(expected[1] + 0.5)) // 16)
        hits += 1
    assert hits >= 2


def test_reduced_decode_matches_full_decode() -> None:
    """The 1/2 DCT decode with its scale folded into the warp gives the same input as a full decode."""
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (900, 1600, 3), dtype=np.uint8), (0, 0), 4)
    jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].ravel()
    aug = sample_image_aug(ImageAugConfig(), 1600, 900, rng)
    assert choose_reduce(aug.scale, 1.0, 1.1) == 2
    half = decode_augmented(jpeg, aug.matrix, aug.scale, 1600, 900, 704, 256)
    full = decode_augmented(jpeg, aug.matrix, aug.scale, 1600, 900, 704, 256, max_upsample=0.5)
    inside = half.sum(-1) > 0
    diff = np.abs(half.astype(int) - full.astype(int))[inside]
    assert diff.mean() < 1.5


def test_test_mode_is_the_fixed_resize_and_bottom_crop() -> None:
    aug = sample_image_aug(ImageAugConfig(train=False), 1600, 900, None)
    s = 704 / 1600
    np.testing.assert_allclose(aug.matrix, [[s, 0, 0], [0, s, -(int(900 * s) - 256)], [0, 0, 1]])


@pytest.mark.parametrize("seed", range(6))
def test_bev_aug_moves_labels_with_the_geometry(seed: int) -> None:
    rng = np.random.default_rng(seed)
    bev = sample_bev_aug(BevAugConfig(flip_x_p=0.5, flip_y_p=0.5, rot_deg=30.0 * (seed % 2), scale=(0.95, 1.05)),
                         rng) if seed % 3 else BevAug(flip_x=True, flip_y=bool(seed % 2))
    sem = np.full(GRID.shape, 17, np.uint8)
    bits = np.zeros(GRID.shape[:2], np.uint32)
    centres = GRID.voxel_centers()
    for label in range(1, 6):
        i, j, k = rng.integers(20, 180), rng.integers(20, 180), rng.integers(0, 16)
        sem[i - 1: i + 2, j - 1: j + 2, k] = label  # 3x3 patch: nearest resampling keeps the centre
        bits[i, j] |= 1 << label
        p = centres[i, j, k]
        q = (bev.matrix @ np.append(p, 1))[:3]
        a, b, c = GRID.index_of(q[None])[0]
        assert apply_bev_aug(sem, bev, 255)[a, b, c] == label
        if bev.is_flip_only:  # flips are exact index permutations, BEV GT included
            moved = apply_bev_aug(bits[None], bev, 0, xy_axes=(1, 2))[0]
            assert moved[a, b] == bits[i, j]
    if bev.is_flip_only:
        back = apply_bev_aug(apply_bev_aug(sem, bev, 255), bev, 255)  # flips are involutions
        np.testing.assert_array_equal(back, sem)
