"""LiDAR points -> camera pixels with the nuScenes devkit's conventions (DESIGN §2)."""

from __future__ import annotations

import numpy as np

from occdata.geometry import project_points, transform_points

__all__ = ["project_lidar_to_image"]


def project_lidar_to_image(
    points_lidar: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    min_depth: float = 1.0,
    margin: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project LiDAR points `(N, >=3)` into one image, devkit style.

    Keeps depth > `min_depth` and `margin < u < width - margin`, `margin < v < height - margin`
    (the devkit's `map_pointcloud_to_image` uses 1.0 and 1 pixel). Returns
    `uv_img (M, 2) float64`, `depth (M,) float64` (camera z) and `keep (N,) bool`.
    """
    points_cam = transform_points(T_cam_from_lidar, np.asarray(points_lidar)[:, :3])
    uv, depth = project_points(K, points_cam)
    with np.errstate(invalid="ignore"):
        keep = (
            (depth > min_depth)
            & (uv[:, 0] > margin)
            & (uv[:, 0] < width - margin)
            & (uv[:, 1] > margin)
            & (uv[:, 1] < height - margin)
        )
    return uv[keep], depth[keep], keep
