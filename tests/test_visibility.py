"""Visibility kernels agree with their numpy twins and with hand-computed cases (docs/design.md#visibility-masks)."""

from __future__ import annotations

import numpy as np
import pytest
from reference.visibility_masks import (
    camera_mask_reference,
    clearance_map_reference,
    count_occluders_reference,
    lidar_ray_mask_reference,
)

from occdata.constants import FREE_LABEL
from occdata.visibility import camera_mask, clearance_map, count_occluders, lidar_mask, lidar_ray_mask

LOWER = np.array([-2.0, -2.4, -0.8])
VS = 0.4


def _camera(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random camera inside the grid looking roughly along +x: `T_cam_from_grid`, K."""
    yaw = rng.uniform(-0.6, 0.6)
    pitch = rng.uniform(-0.3, 0.3)
    fwd = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R_grid_from_cam = np.stack([right, down, fwd], axis=1)
    centre = np.array([rng.uniform(-1.9, -1.0), rng.uniform(-0.5, 0.5), rng.uniform(0.0, 1.0)])
    T = np.eye(4)
    T[:3, :3] = R_grid_from_cam.T
    T[:3, 3] = -R_grid_from_cam.T @ centre
    K = np.array([[30.0, 0.0, 31.5], [0.0, 30.0, 19.5], [0.0, 0.0, 1.0]])
    return T, K


@pytest.mark.parametrize("seed", range(4))
def test_count_occluders_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    occ = rng.random((14, 12, 7)) < 0.2
    occ[:8] = rng.random((8, 12, 7)) < 0.01  # mostly empty near the camera: the skip has room
    occ = occ.astype(np.uint8)
    T, K = _camera(rng)
    cam = -T[:3, :3].T @ T[:3, 3]
    occ[tuple(np.floor((cam - LOWER) / VS).astype(int))] = 0  # the camera sits in a free voxel
    targets = np.argwhere(np.ones(occ.shape, bool)).astype(np.int64)
    clear = clearance_map(occ, 16)
    assert clear.max() >= 3  # the empty-space skip is exercised
    for cap in (0, 3, 100):
        got = count_occluders(occ, clear, targets, T, K, 64, 40, LOWER, VS, cap)
        ref = count_occluders_reference(occ, clear, targets, T, K, 64, 40, LOWER, VS, cap)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(count_occluders(occ, np.zeros_like(occ), targets, T, K, 64, 40, LOWER, VS, cap),
                                      ref)
    assert (got == -1).any() and (got == 0).any() and (got >= 3).any()  # outside, clear and deep targets


def test_count_occluders_hand_computed() -> None:
    """Camera on the x axis looking along +x at walls in planes x = 10, 12, 14 (voxel indices)."""
    occ = np.zeros((20, 5, 5), np.uint8)
    occ[[10, 12, 14], :, :] = 1
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # cam z = grid x
    centre = np.array([0.2, 1.0, 1.0])
    T[:3, 3] = -T[:3, :3] @ centre
    K = np.array([[10.0, 0.0, 49.5], [0.0, 10.0, 49.5], [0.0, 0.0, 1.0]])
    targets = np.array([[i, 2, 2] for i in range(20)], np.int64)
    got = count_occluders(occ, clearance_map(occ, 8), targets, T, K, 100, 100, np.zeros(3), VS, 10)
    # voxel 0 holds the camera (centre at depth 0: not in front); the walls count before the target only
    expect = [-1] + [0] * 10 + [1, 1, 2, 2, 3, 3, 3, 3, 3]
    np.testing.assert_array_equal(got, expect)
    assert count_occluders(occ, np.zeros_like(occ), targets, T, K, 100, 100, np.zeros(3), VS, 1)[-1] == 2  # cap + 1


def test_camera_mask_semantics() -> None:
    """Within mask_lidar: free and ground voxels pass; objects pass with at most max_occluders before them."""
    sem = np.full((20, 5, 5), FREE_LABEL, np.uint8)
    sem[:, :, 0] = 11  # road
    sem[10:18, 1:4, 1:4] = 15  # a building block 8 voxels deep
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    T[:3, 3] = -T[:3, :3] @ np.array([0.2, 1.0, 1.0])
    K = np.array([[10.0, 0.0, 49.5], [0.0, 10.0, 49.5], [0.0, 0.0, 1.0]])
    lidar = np.ones(sem.shape, np.uint8)
    lidar[:, 4, :] = 0
    size = np.array([[100, 100]])
    m = camera_mask(sem, lidar, K[None], T[None], size, np.zeros(3), VS, max_occluders=2)
    assert not (m & ~lidar.astype(bool)).any()  # within the LiDAR mask
    assert m[:, :4, 0].all()  # the road is visible where observed, whatever lies before it
    assert (m[(sem == FREE_LABEL) & (lidar == 1)] == 1).all()
    assert m[10:13, 2, 2].all() and not m[13:18, 2, 2].any()  # 0, 1, 2 block voxels before: visible
    strict = camera_mask(sem, lidar, K[None], T[None], size, np.zeros(3), VS, max_occluders=0)
    assert strict[10, 2, 2] == 1 and not strict[11:18, 2, 2].any()


@pytest.mark.parametrize("seed", range(3))
def test_lidar_ray_mask_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = np.array([12, 10, 6], np.int64)
    origins = np.repeat(rng.uniform(LOWER + 0.5, LOWER + 1.5)[None], 40, axis=0)
    ends = rng.uniform(LOWER - 1.0, LOWER + shape * VS + 1.0, (40, 3))
    ends[:5] = origins[:5] + rng.uniform(-0.3, 0.3, (5, 3))  # short rays
    ends[5:8, 2] = origins[5:8, 2]  # horizontal rays
    origins[8:10] = rng.uniform(LOWER - 3.0, LOWER - 2.0, (2, 3))  # starting outside the grid
    got = lidar_ray_mask(origins, ends, LOWER, VS, shape)
    ref = lidar_ray_mask_reference(origins, ends, LOWER, VS, shape)
    np.testing.assert_array_equal(got, ref)
    assert got.sum() > 40


def test_lidar_mask_adds_every_object_voxel() -> None:
    sem = np.full((10, 10, 4), FREE_LABEL, np.uint8)
    sem[:, :, 0] = 11
    sem[7, 7, 1:3] = 4  # a car no ray reaches
    o = np.array([[0.2, 2.0, 0.6]])
    e = np.array([[3.8, 2.0, 0.6]])
    m = lidar_mask(sem, o, e, np.zeros(3), VS)
    assert m[7, 7, 1:3].all() and m[:10, 5, 1].sum() == 10 and m.sum() == 12
    assert not m[:, :, 0].any()  # ground only where a ray reached it


@pytest.mark.parametrize("seed", range(3))
def test_camera_mask_matches_reference(seed: int) -> None:
    """The composed mask (6 cameras, early exits, deep-interior pre-filter) equals the brute-force twin."""
    rng = np.random.default_rng(100 + seed)
    sem = np.full((16, 14, 8), FREE_LABEL, np.uint8)
    sem[:, :, 0] = rng.choice([11, 13, 14], size=(16, 14))
    sem[rng.random(sem.shape) < 0.08] = 16
    sem[9:16, 3:12, 1:8] = 15  # a solid block, deep enough for the pre-filter to drop its core
    lidar = (rng.random(sem.shape) < 0.7).astype(np.uint8)
    cams = [_camera(rng) for _ in range(3)]
    T = np.stack([c[0] for c in cams])
    K = np.stack([c[1] for c in cams])
    for c in range(3):
        cam = -T[c, :3, :3].T @ T[c, :3, 3]
        sem[tuple(np.floor((cam - LOWER) / VS).astype(int))] = FREE_LABEL
    size = np.array([[64, 40]] * 3)
    for n in (0, 2):
        got = camera_mask(sem, lidar, K, T, size, LOWER, VS, max_occluders=n)
        ref = camera_mask_reference(sem, lidar, K, T, size, LOWER, VS, max_occluders=n)
        np.testing.assert_array_equal(got, ref)
        obj = (sem != FREE_LABEL) & ~np.isin(sem, (11, 13, 14))
        assert 10 < (got.astype(bool) & obj).sum() < (obj & (lidar == 1)).sum()


@pytest.mark.parametrize("seed", range(3))
def test_clearance_map_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    occ = (rng.random((23, 17, 9)) < [0.002, 0.02, 0.2][seed]).astype(np.uint8)
    for r in (1, 4, 16):
        np.testing.assert_array_equal(clearance_map(occ, r), clearance_map_reference(occ, r))
    assert clearance_map(np.zeros((5, 5, 5), np.uint8), 7).min() == 7
