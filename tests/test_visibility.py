"""Voxel traversal kernels (camera visibility, LiDAR mask) agree with their numpy twins."""

from __future__ import annotations

import numpy as np
import pytest

from occdata.visibility import (
    camera_visible_mask,
    camera_visible_mask_reference,
    lidar_ray_mask,
    lidar_ray_mask_reference,
)

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
def test_camera_visible_mask_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    occ = (rng.random((14, 12, 7)) < 0.06).astype(np.uint8)
    T, K = _camera(rng)
    cam = -T[:3, :3].T @ T[:3, 3]
    occ[tuple(np.floor((cam - LOWER) / VS).astype(int))] = 0  # the camera sits in a free voxel
    got = camera_visible_mask(occ, T, K, 64, 40, LOWER, VS)
    ref = camera_visible_mask_reference(occ, T, K, 64, 40, LOWER, VS)
    np.testing.assert_array_equal(got, ref)
    assert 20 < got.sum() < got.size


def test_camera_mask_semantics() -> None:
    """A wall hides what is behind it; free voxels in front of it and the wall itself are visible."""
    occ = np.zeros((20, 5, 5), np.uint8)
    occ[10, :, :] = 1
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # cam z = grid x
    centre = np.array([0.2, 1.0, 1.0])
    T[:3, 3] = -T[:3, :3] @ centre
    K = np.array([[10.0, 0.0, 49.5], [0.0, 10.0, 49.5], [0.0, 0.0, 1.0]])
    m = camera_visible_mask(occ, T, K, 100, 100, np.zeros(3), VS)
    assert m[1:10, 2, 2].all() and m[10, 2, 2] == 1 and not m[11:, :, :].any() and not m[0].any()


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
