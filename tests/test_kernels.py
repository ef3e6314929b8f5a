"""Each numba kernel agrees with its numpy twin on random inputs; hand-checked small cases."""

from __future__ import annotations

import numpy as np
from reference.sensors_projection import project_to_cameras_reference
from reference.store_bev import bev_bits_reference

from occdata.geometry import invert_rigid, transform_from_pose
from occdata.sensors.projection import project_lidar_to_image, project_to_cameras
from occdata.store.bev import bev_bits, unpack_bev


def _random_rig(rng: np.random.Generator, n_cam: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    T = np.empty((n_cam, 4, 4))
    K = np.zeros((n_cam, 3, 3))
    for c in range(n_cam):
        q = rng.normal(size=4)
        T[c] = invert_rigid(transform_from_pose(rng.normal(size=3), q / np.linalg.norm(q)))
        f = rng.uniform(300, 1500)
        K[c] = [[f, 0, rng.uniform(300, 900)], [0, f, rng.uniform(200, 500)], [0, 0, 1]]
    sizes = np.tile(np.array([[1600, 900]], dtype=np.int64), (n_cam, 1))
    return T, K, sizes


def test_projection_kernel_matches_twin_bitwise() -> None:
    rng = np.random.default_rng(0)
    for trial in range(5):
        pts = (rng.normal(size=(5000, 5)) * 20).astype(np.float32)
        T, K, sizes = _random_rig(rng, 6)
        min_depth = [0.0, 1.0, 0.5, 2.0, 0.1][trial]
        uvd, counts = project_to_cameras(pts, T, K, sizes, min_depth)
        uvd_ref, counts_ref = project_to_cameras_reference(pts, T, K, sizes, min_depth)
        assert counts.tolist() == counts_ref.tolist()
        assert counts.sum() > 100
        for c in range(6):
            np.testing.assert_array_equal(uvd[c, : counts[c]], uvd_ref[c, : counts[c]])


def test_projection_kernel_agrees_with_devkit_chain() -> None:
    rng = np.random.default_rng(3)
    pts = (rng.normal(size=(20000, 3)) * 15).astype(np.float32)
    T, K, sizes = _random_rig(rng, 3)
    uvd, counts = project_to_cameras(pts, T, K, sizes, 1.0)
    for c in range(3):
        uv, depth, _ = project_lidar_to_image(pts, T[c], K[c], 1600, 900, min_depth=1.0, margin=0.0)
        # The devkit keeps 0 < u < W; the store keeps 0 <= u < W: equal except on exact zeros.
        assert counts[c] == len(depth)
        np.testing.assert_allclose(uvd[c, : counts[c], :2], uv, rtol=0, atol=1e-3)
        np.testing.assert_allclose(uvd[c, : counts[c], 2], depth, rtol=1e-6)


def test_projection_hand_case() -> None:
    # Identity extrinsics, f = 100, principal point (50, 40), image 100 x 80.
    K = np.array([[[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]])
    T = np.eye(4)[None]
    # Kept: on-axis point and (0.5, 0.5, 2) -> (75, 65). Dropped: behind, outside (u = 550),
    # too near (depth 0.5), and u = W exactly (1, 0, 2) -> u = 100.
    pts = np.array([[0, 0, 2], [0.5, 0.5, 2], [0, 0, -2], [10, 0, 2], [0, 0, 0.5], [1, 0, 2]], dtype=np.float32)
    uvd, counts = project_to_cameras(pts, T, K, np.array([[100, 80]]), 1.0)
    assert counts[0] == 2
    np.testing.assert_allclose(uvd[0, :2], [[50, 40, 2], [75, 65, 2]])


def test_bev_kernel_matches_twin_and_hand_case() -> None:
    rng = np.random.default_rng(0)
    sem = rng.integers(0, 18, size=(20, 30, 16), dtype=np.uint8)
    sem[0, 0] = 17
    np.testing.assert_array_equal(bev_bits(sem), bev_bits_reference(sem))
    small = np.full((2, 1, 4), 17, dtype=np.uint8)
    small[0, 0, :2] = [4, 11]  # car over driveable surface, free above
    bits = bev_bits(small)
    assert bits[0, 0] == (1 << 4) | (1 << 11) | (1 << 17)
    assert bits[1, 0] == 1 << 17
    multi = unpack_bev(bits)
    assert multi.shape == (18, 2, 1)
    assert multi[:, 0, 0].nonzero()[0].tolist() == [4, 11, 17]
