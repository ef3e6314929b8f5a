import numpy as np

from occdata.constants import GRID
from occdata.geometry import (
    invert_rigid,
    quaternion_wxyz_from_matrix,
    rotation_from_quaternion_wxyz,
    transform_from_pose,
    transform_points,
)


def _random_rigid(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return transform_from_pose(rng.normal(size=3) * 10, q)


def test_invert_rigid_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        T = _random_rigid(rng)
        np.testing.assert_allclose(invert_rigid(T) @ T, np.eye(4), atol=1e-12)
        pts = rng.normal(size=(50, 3)) * 20
        np.testing.assert_allclose(transform_points(invert_rigid(T), transform_points(T, pts)), pts, atol=1e-9)


def test_quaternion_round_trip_and_hand_case() -> None:
    # 90 deg yaw about z: x -> y.
    R = rotation_from_quaternion_wxyz([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = rotation_from_quaternion_wxyz(q)
        np.testing.assert_allclose(rotation_from_quaternion_wxyz(quaternion_wxyz_from_matrix(R)), R, atol=1e-9)


def test_grid_centres_match_design() -> None:
    assert GRID.shape == (200, 200, 16)
    c = GRID.voxel_centers()
    np.testing.assert_allclose(c[0, 0, 0], [-39.8, -39.8, -0.8], atol=1e-5)
    np.testing.assert_allclose(c[199, 199, 15], [39.8, 39.8, 5.2], atol=1e-5)
    idx = GRID.index_of(c.reshape(-1, 3)[[0, 12345, -1]])
    assert idx.tolist() == [[0, 0, 0], list(np.unravel_index(12345, GRID.shape)), [199, 199, 15]]
