"""A scene's LiDAR frames and their points in the global frame: each frame through its own calibration
and ego pose (motion compensation per frame; with a `PoseTrack`, per point where the file has per-point
times, `occdata.labels.deskew`), the points on the ego car set apart; the rays of a keyframe (`Rays`,
each LiDAR from its own origin); the grids' frames."""

from __future__ import annotations

import numpy as np

from occdata.constants import EGO_BOX
from occdata.formats.gridspec import GridSpec, LabelFrame
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.deskew import PoseTrack, deskew_points
from occdata.nuscenes import LidarRecord, NuScenesDataset, SampleRecord, load_lidar_points
from occdata.nuscenes.pointfiles import is_pcd, read_pcd

__all__ = ["Frame", "Rays", "T_grid_from_keyego", "frame_points", "off_ego_rays", "rays_in", "scene_frames",
           "scene_track"]

Frame = tuple[int, int, LidarRecord]  # (sample index, LiDAR index in rig order, record)
Rays = list[tuple[np.ndarray, np.ndarray]]  # a keyframe's rays per LiDAR: (origin (3,), points (N, 3)), global


def frame_points(rec: LidarRecord, track: PoseTrack | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A frame's points `(N, 3) float64` in global, the lidar origin in global `(3,)`, and
    `(N,) bool` off the ego car. With `track`, a `.pcd` file's per-point times place each point by the
    ego pose of its time (`deskew_points`; the ego car's own points are told apart before: they ride
    with the ego)."""
    if track is not None and is_pcd(rec.path):
        pcd = read_pcd(rec.path)
        raw, times = pcd.points[:, :3].astype(np.float64), pcd.timestamps
    else:
        raw, times = load_lidar_points(rec.path)[:, :3].astype(np.float64), None
    points_ego = transform_points(rec.T_ego_from_lidar, raw)
    lo, hi = np.array(EGO_BOX[0]), np.array(EGO_BOX[1])
    off_ego = ~((points_ego >= lo) & (points_ego <= hi)).all(axis=1)
    if times is not None:
        points_ego = deskew_points(raw, times, rec.timestamp, rec.T_ego_from_lidar, rec.T_global_from_ego, track,
                                   str(rec.path))
    T_global_from_lidar = rec.T_global_from_ego @ rec.T_ego_from_lidar
    return transform_points(rec.T_global_from_ego, points_ego), T_global_from_lidar[:3, 3].copy(), off_ego


def off_ego_rays(rec: LidarRecord, track: PoseTrack | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A frame's LiDAR origin `(3,)` and its points off the ego car `(N, 3)`, float64 in global
    (`frame_points`; the origin is the sweep's, also for deskewed points)."""
    points, origin, off_ego = frame_points(rec, track)
    return origin, points[off_ego]


def scene_frames(ds: NuScenesDataset, indices: list[int], sweeps: bool) -> list[Frame]:
    """Every LiDAR frame of the scene (samples `indices`) as `Frame`s: keyframes, then (with `sweeps`)
    each keyframe's sweeps of each LiDAR."""
    out = [(i, k, rec) for i in indices for k, rec in enumerate(ds.samples[i].lidars)]
    if sweeps:
        out += [(i, k, rec) for i in indices for k in range(len(ds.samples[i].lidars))
                for rec in ds.samples[i].sweeps_of(k)]
    return out


def scene_track(ds: NuScenesDataset, indices: list[int]) -> PoseTrack:
    """The ego poses of samples `indices` that the tables give: every LiDAR frame's (keyframes and
    sweeps read) and every camera's, by timestamp (`deskew_points` interpolates between them)."""
    poses = []
    for i in indices:
        s = ds.samples[i]
        recs = [*s.lidars, *(r for k in range(len(s.lidars)) for r in s.sweeps_of(k))]
        poses += [(r.timestamp, r.T_global_from_ego) for r in recs]
        poses += [(c.timestamp, c.T_global_from_ego) for c in s.cameras]
    return PoseTrack.of(poses)


def rays_in(T: np.ndarray, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
    """Every LiDAR's rays of a keyframe moved by `T (4, 4)`: origins and endpoints `(N, 3) float64`
    (one LiDAR: its origin broadcast, as before several LiDARs were read)."""
    ends = [transform_points(T, pts) for _, pts in rays]
    origins = [np.broadcast_to(transform_points(T, o[None])[0], e.shape) for (o, _), e in zip(rays, ends, strict=True)]
    if len(rays) == 1:
        return origins[0], ends[0]
    return np.concatenate(origins), np.concatenate(ends)


def T_grid_from_keyego(sample: SampleRecord, spec: GridSpec) -> np.ndarray:
    """`(4, 4) float64`: the keyframe's key ego -> the grid's frame (itself, or the LIDAR_TOP sensor)."""
    if spec.frame is LabelFrame.LIDAR:
        return invert_rigid(sample.lidar.T_ego_from_lidar)  # the keyframe sweep's ego is the key ego
    return np.eye(4)
