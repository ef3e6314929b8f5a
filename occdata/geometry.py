"""Rigid transforms named by frames: `T_b_from_a @ p_a = p_b` (docs/design.md#frames-and-names)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pyquaternion import Quaternion

__all__ = [
    "invert_rigid",
    "points_in_box",
    "project_points",
    "quaternion_problem",
    "quaternion_wxyz_from_matrix",
    "rotation_from_quaternion_wxyz",
    "transform_from_pose",
    "transform_points",
]


def rotation_from_quaternion_wxyz(q_wxyz: Sequence[float] | np.ndarray, normalise: bool = True) -> np.ndarray:
    """3x3 rotation `(3, 3) float64` of a nuScenes quaternion `[w, x, y, z]`, normalised first.

    The one quaternion-to-matrix rule of the package (calibrations, poses, boxes, the synthetic rig).
    `normalise=False` keeps a non-unit quaternion's scale, so a rigidity check downstream can reject it."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    # Quietly: a bad quaternion gives NaN/inf entries that the caller's check names (no numpy warning).
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        # Python floats below (the same IEEE arithmetic; numpy scalars made this 5x slower, once per pose)
        w, x, y, z = (q / np.linalg.norm(q) if normalise else q).tolist()
        return np.array([
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ])


QUATERNION_LENGTH_MAX = 1e3  # a file's rotation quaternion has length 1 up to rounding; 1000 is no rounding


def quaternion_problem(q_wxyz: Sequence[float] | np.ndarray) -> str | None:
    """What makes `[w, x, y, z]` unusable as a rotation before any arithmetic on it, for an error
    message ("is not finite", "is implausibly large (|q| = 1e+300 ...)"), or None. Computed without
    numpy warnings (|q| of 1e300 overflows a plain norm). A moderately non-unit quaternion is None:
    the rigidity check of its matrix reports it."""
    q = np.asarray(q_wxyz, dtype=np.float64).ravel().tolist()  # Python floats: a pose's check is ~1 us
    if not all(math.isfinite(v) for v in q):
        return "is not finite (NaN or inf)"
    scale = max((abs(v) for v in q), default=0.0)
    length = scale * math.sqrt(sum((v / scale) ** 2 for v in q)) if scale > 0 else 0.0
    if length > QUATERNION_LENGTH_MAX:
        return f"is implausibly large (|q| = {length:.3g}; a rotation's quaternion has length 1)"
    return None


def quaternion_wxyz_from_matrix(R: np.ndarray) -> list[float]:
    """`[w, x, y, z]` of a rotation matrix; w >= 0 so the output is unique."""
    q = Quaternion(matrix=np.asarray(R, dtype=np.float64), atol=1e-6, rtol=1e-6)
    wxyz = [float(q.w), float(q.x), float(q.y), float(q.z)]
    return [-v for v in wxyz] if wxyz[0] < 0 else wxyz


def transform_from_pose(translation: Sequence[float], rotation_wxyz: Sequence[float]) -> np.ndarray:
    """4x4 `float64` transform of a nuScenes (translation, rotation) record.

    A calibrated_sensor record gives `T_ego_from_sensor`; an ego_pose record gives `T_global_from_ego`.
    """
    T = np.eye(4)
    T[:3, :3] = rotation_from_quaternion_wxyz(rotation_wxyz)
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def invert_rigid(T_b_from_a: np.ndarray) -> np.ndarray:
    """Exact inverse `T_a_from_b` of a rigid 4x4 transform (R^T, -R^T t)."""
    R = T_b_from_a[..., :3, :3]
    t = T_b_from_a[..., :3, 3]
    out = np.zeros_like(T_b_from_a)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def points_in_box(points_a: np.ndarray, T_box_from_a: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """`(N,) bool`: which points `(N, 3)` lie in the closed box `|p_box| <= half_size (3,)` (x along the
    box's length, y its width, z its height), the box frame given by `T_box_from_a (4, 4)`.

    The one membership rule: the labels generator's kernel has this as its numpy twin, the fidelity
    measures and the synthetic annotations' point counts use it directly."""
    p = points_a @ T_box_from_a[:3, :3].T + T_box_from_a[:3, 3]
    return (np.abs(p) <= half_size).all(axis=1)


def transform_points(T_b_from_a: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points `(N, 3)`; returns `(N, 3)` in frame b (float64)."""
    p = np.asarray(points_a, dtype=np.float64)
    return p @ T_b_from_a[:3, :3].T + T_b_from_a[:3, 3]


def project_points(K: np.ndarray, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of camera-frame points `(N, 3)`.

    Returns `uv_img (N, 2) float64` (pixels; x right, y down) and `depth (N,) float64` (camera z).
    Points with depth <= 0 get NaN pixel coordinates.
    """
    p = np.asarray(points_cam, dtype=np.float64)
    depth = p[:, 2].copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = p @ np.asarray(K, dtype=np.float64).T
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[depth <= 0] = np.nan
    return uv, depth
