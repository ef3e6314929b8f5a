"""Motion inside a sweep: a spinning LiDAR takes ~100 ms a turn, and a truck at 22 m/s moves 2 m in it.

A point file with per-point times (a PCD `timestamp` field, microseconds like the tables: TruckScenes'
layout) lets each point be placed by the ego pose of its own time instead of the sweep's: the ego pose
at time t is interpolated between the scene's poses (`PoseTrack`: position linear, heading by the
rotation between the two poses scaled by the time fraction), and the point, so placed in global, is
moved into the ego frame of the sweep's timestamp, as if the whole sweep were taken then.

Only for clouds that are not motion-compensated already: correcting a compensated cloud moves it by
the motion twice. Whether a dataset's clouds are is a fact about the dataset, not the file
(docs/rigs.md); `LabelOptions.deskew` turns the correction on.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from occdata.errors import OccDataError
from occdata.geometry import invert_rigid, transform_points

__all__ = ["MAX_POINT_LAG_US", "PoseTrack", "deskew_points"]

# Per-point times farther than this from their sweep's timestamp are not microseconds of that sweep.
MAX_POINT_LAG_US = 1_000_000


def _log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vectors `(M, 3)` of rotations `R (M, 3, 3)` (angle < pi)."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    skew = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin = np.sin(angle)
    scale = np.where(sin > 1e-9, angle / np.where(sin > 1e-9, 2.0 * sin, 1.0), 0.5)  # small angles: first order
    return skew * scale[:, None]


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotations `(N, 3, 3)` of rotation vectors `w (N, 3)` (Rodrigues)."""
    angle = np.linalg.norm(w, axis=1)
    axis = w / np.where(angle > 1e-12, angle, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = axis[:, 2], -axis[:, 1], axis[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3)[None] + s * K + (1.0 - c) * (K @ K)


@dataclass(frozen=True, eq=False)
class PoseTrack:
    """A scene's ego poses over time: `t_us (P,) int64` strictly increasing, `T_global_from_ego (P, 4, 4)
    float64`; `at(t)` interpolates between them, and beyond the first / last pose carries on the motion
    of the first / last two (a scene's first sweep began before any pose of it)."""

    t_us: np.ndarray
    T_global_from_ego: np.ndarray

    def __post_init__(self) -> None:
        if len(self.t_us) == 0 or self.T_global_from_ego.shape != (len(self.t_us), 4, 4):
            raise ValueError("a PoseTrack needs P >= 1 times and (P, 4, 4) poses")
        if (np.diff(self.t_us) <= 0).any():
            raise ValueError("PoseTrack times must increase strictly")

    @classmethod
    def of(cls, poses: Iterable[tuple[int, np.ndarray]]) -> PoseTrack:
        """From `(timestamp us, T_global_from_ego (4, 4))` pairs in any order; one pose per timestamp."""
        by_time = {int(t): np.asarray(T, np.float64) for t, T in poses}
        times = np.array(sorted(by_time), np.int64)
        return cls(times, np.stack([by_time[int(t)] for t in times]))

    def at(self, t_us: np.ndarray) -> np.ndarray:
        """`(N, 4, 4) float64` ego poses at times `t_us (N,)`."""
        t = np.asarray(t_us, np.float64).reshape(-1)
        if len(self.t_us) == 1:
            return np.broadcast_to(self.T_global_from_ego[0], (len(t), 4, 4)).copy()
        j = np.clip(np.searchsorted(self.t_us, t, side="right") - 1, 0, len(self.t_us) - 2)
        t0, t1 = self.t_us[j].astype(np.float64), self.t_us[j + 1].astype(np.float64)
        alpha = (t - t0) / (t1 - t0)  # < 0 or > 1 outside the track: extrapolated
        R0, R1 = self.T_global_from_ego[j, :3, :3], self.T_global_from_ego[j + 1, :3, :3]
        w = _log_so3(np.transpose(R0, (0, 2, 1)) @ R1)
        out = np.zeros((len(t), 4, 4))
        out[:, :3, :3] = R0 @ _exp_so3(alpha[:, None] * w)
        p0, p1 = self.T_global_from_ego[j, :3, 3], self.T_global_from_ego[j + 1, :3, 3]
        out[:, :3, 3] = p0 + alpha[:, None] * (p1 - p0)
        out[:, 3, 3] = 1.0
        return out


def deskew_points(points_lidar: np.ndarray, t_points_us: np.ndarray, t_sweep_us: int,
                  T_ego_from_lidar: np.ndarray, T_global_from_ego: np.ndarray, track: PoseTrack,
                  name: str = "sweep") -> np.ndarray:
    """Points `(N, 3)` of a LiDAR frame, each taken at `t_points_us (N,)`, in the ego frame of the sweep's
    time `t_sweep_us` (whose pose is `T_global_from_ego (4, 4)`): `(N, 3) float64`. Each point goes
    through the ego pose of its own time (`track.at`). `name`: the file, for the error a point time more
    than `MAX_POINT_LAG_US` from the sweep's raises (not microseconds of this sweep)."""
    t = np.asarray(t_points_us).astype(np.int64)
    lag = np.abs(t - int(t_sweep_us))
    if len(t) and lag.max() > MAX_POINT_LAG_US:
        raise OccDataError(f"{name}: per-point timestamp {int(t[int(np.argmax(lag))])} is {int(lag.max()):,} us from "
                           f"the sweep's {int(t_sweep_us)}: not microseconds of this sweep")
    points_ego_t = transform_points(T_ego_from_lidar, np.asarray(points_lidar, np.float64))
    T = track.at(t)
    points_global = np.einsum("nij,nj->ni", T[:, :3, :3], points_ego_t) + T[:, :3, 3]
    return transform_points(invert_rigid(T_global_from_ego), points_global)
