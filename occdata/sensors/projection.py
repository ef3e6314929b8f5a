"""LiDAR points -> camera pixels (docs/design.md#frames-and-names, #the-store-layout).

`project_to_cameras` is the numba kernel the store build uses (all cameras in one pass, float64
arithmetic, float32 output); `project_to_cameras_reference` (tests/reference/) is its plain numpy twin with the same
arithmetic order, so the two agree bit for bit. `project_lidar_to_image` is the devkit-style chain
(per camera, matrix products) that the tests check against the devkit's published point counts.
"""

from __future__ import annotations

import numba
import numpy as np

from occdata.geometry import project_points, transform_points

__all__ = ["project_lidar_to_image", "project_to_cameras"]


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


@numba.njit(cache=True, nogil=True)
def _camera_matrices(T_cam_from_lidar: np.ndarray, K: np.ndarray) -> np.ndarray:
    """`(C, 3, 4) float64` P = K @ T[:3, :] per camera, by explicit sums (same order as the twin)."""
    n_cam = K.shape[0]
    P = np.empty((n_cam, 3, 4))
    for c in range(n_cam):
        for r in range(3):
            for j in range(4):
                P[c, r, j] = K[c, r, 0] * T_cam_from_lidar[c, 0, j] + K[c, r, 1] * T_cam_from_lidar[c, 1, j] + (
                    K[c, r, 2] * T_cam_from_lidar[c, 2, j]
                )
    return P


@numba.njit(cache=True, nogil=True, error_model="numpy")  # IEEE division: no zero-check branch
def project_to_cameras(
    points_lidar: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    K: np.ndarray,
    sizes: np.ndarray,
    min_depth: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Project LiDAR points into every camera; keep depth > min_depth, 0 <= u < W, 0 <= v < H.

    points_lidar `(N, >=3) float32`; T_cam_from_lidar `(C, 4, 4) float64`; K `(C, 3, 3) float64`;
    sizes `(C, 2) int64` (W, H). Returns `uvd (C, N, 3) float32` (first counts[c] rows valid,
    in point order) and `counts (C,) int64`. Depth is camera z; u, v use P = K @ T and one
    reciprocal per point (float64 throughout).
    """
    n = points_lidar.shape[0]
    n_cam = K.shape[0]
    P = _camera_matrices(T_cam_from_lidar, K)
    uvd = np.empty((n_cam, n, 3), dtype=np.float32)
    counts = np.zeros(n_cam, dtype=np.int64)
    # Points outer, cameras inner: each point is loaded once and most cameras reject it on depth.
    # Coefficients live in flat 2D arrays indexed directly (no per-camera views in the hot loop).
    Tz = np.ascontiguousarray(T_cam_from_lidar[:, 2, :])
    Pf = np.ascontiguousarray(P.reshape(n_cam, 12))
    wh = sizes.astype(np.float64)
    for i in range(n):
        x = np.float64(points_lidar[i, 0])
        y = np.float64(points_lidar[i, 1])
        z = np.float64(points_lidar[i, 2])
        for c in range(n_cam):
            zc = Tz[c, 0] * x + Tz[c, 1] * y + Tz[c, 2] * z + Tz[c, 3]
            if not zc > min_depth:
                continue
            inv = 1.0 / (Pf[c, 8] * x + Pf[c, 9] * y + Pf[c, 10] * z + Pf[c, 11])
            u = (Pf[c, 0] * x + Pf[c, 1] * y + Pf[c, 2] * z + Pf[c, 3]) * inv
            if not (u >= 0.0 and u < wh[c, 0]):
                continue
            v = (Pf[c, 4] * x + Pf[c, 5] * y + Pf[c, 6] * z + Pf[c, 7]) * inv
            if v >= 0.0 and v < wh[c, 1]:
                m = counts[c]
                uvd[c, m, 0] = u
                uvd[c, m, 1] = v
                uvd[c, m, 2] = zc
                counts[c] = m + 1
    return uvd, counts
