"""The reader on the REAL nuScenes keyframe in ../shared/data (read-only, never copied)."""

from __future__ import annotations

import numpy as np
import pytest

from occdata.constants import CAMERA_ORDER
from occdata.geometry import invert_rigid
from occdata.nuscenes import load_lidar_points, load_nuscenes, validate_sample
from occdata.sensors.projection import project_lidar_to_image

# The official devkit's map_pointcloud_to_image (min_dist 1.0) on this real keyframe.
DEVKIT_COUNTS = {
    "CAM_FRONT": 3053,
    "CAM_FRONT_RIGHT": 3076,
    "CAM_FRONT_LEFT": 3696,
    "CAM_BACK": 4820,
    "CAM_BACK_LEFT": 4089,
    "CAM_BACK_RIGHT": 3369,
}


@pytest.fixture(scope="module")
def real(real_nuscenes_root):
    return load_nuscenes(real_nuscenes_root, "v1.0-mini", check_files=True)


def test_reads_real_keyframe(real) -> None:
    assert real.version == "v1.0-mini"
    assert [s.name for s in real.scenes] == ["scene-0061"]
    assert real.scenes[0].split == "mini_train"
    assert real.scenes[0].location == "singapore-onenorth"
    (sample,) = real.samples
    assert sample.token == "ca9a282c9e77460f8360f564131a8af5"
    assert tuple(c.channel for c in sample.cameras) == CAMERA_ORDER
    assert all((c.width, c.height) == (1600, 900) and c.path.is_file() for c in sample.cameras)
    # Cameras fire within ~45 ms around the LiDAR keyframe, each with its own ego pose.
    offsets = [abs(c.timestamp - sample.lidar.timestamp) for c in sample.cameras]
    assert max(offsets) < 50_000
    assert len({c.T_global_from_ego[0, 3] for c in sample.cameras}) == 6
    validate_sample(sample)


def test_version_is_autodetected(real_nuscenes_root) -> None:
    assert load_nuscenes(real_nuscenes_root).version == "v1.0-mini"


def test_rig_geometry_is_plausible(real) -> None:
    sample = real.samples[0]
    # LiDAR frame: x right, y forward -> a yaw of about -90 deg to ego (x forward).
    R = sample.lidar.T_ego_from_lidar[:3, :3]
    np.testing.assert_allclose(R @ [0, 1, 0], [1, 0, 0], atol=0.05)
    front = sample.cameras[CAMERA_ORDER.index("CAM_FRONT")]
    # Camera optical axis (z) of CAM_FRONT points along ego +x.
    np.testing.assert_allclose(front.T_ego_from_cam[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=0.05)
    # key-ego chain: camera position in key ego differs from its own-ego position by the ego motion only.
    for i in range(6):
        T = sample.T_keyego_from_cam(i)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.norm(T[:3, 3] - sample.cameras[i].T_ego_from_cam[:3, 3]) < 0.6


def test_lidar_projection_matches_devkit_counts(real) -> None:
    sample = real.samples[0]
    points = load_lidar_points(sample.lidar.path)
    assert points.shape == (34688, 5) and points.dtype == np.float32
    for i, cam in enumerate(sample.cameras):
        uv, depth, _ = project_lidar_to_image(points, sample.T_cam_from_lidar(i), cam.K, cam.width, cam.height)
        assert len(depth) == DEVKIT_COUNTS[cam.channel], cam.channel
        assert depth.min() > 1.0


def test_cam_from_lidar_chain_is_consistent(real) -> None:
    sample = real.samples[0]
    for i in range(len(sample.cameras)):
        via_keyego = invert_rigid(sample.T_keyego_from_cam(i)) @ sample.lidar.T_ego_from_lidar
        np.testing.assert_allclose(sample.T_cam_from_lidar(i), via_keyego, atol=1e-9)
