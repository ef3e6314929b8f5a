"""`synthesize(config)`: write a complete nuScenes-format tree of a synthetic world with Occ3D labels."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from occdata.constants import GRID, LIDAR_CHANNEL, OccGrid
from occdata.errors import OccDataError
from occdata.formats.gridfiles import LabelSite, write_grid_label
from occdata.formats.gridspec import GridSpec, LabelFrame
from occdata.formats.imagemasks import mask_path
from occdata.formats.occ3d import label_path, write_label
from occdata.geometry import invert_rigid, quaternion_wxyz_from_matrix, transform_points
from occdata.synth import render
from occdata.synth.annotations import (
    LIDARSEG_FROM_OCC3D,
    KeyframeAnnotation,
    ObjectBoxes,
    annotate_keyframe,
    annotation_rows,
    object_boxes,
)
from occdata.synth.gridtruth import grid_semantics
from occdata.synth.labels import world_semantics
from occdata.synth.rig import NUSCENES, RIGS, LidarSpec, SynthRig
from occdata.synth.tables import make_token, static_tables, write_atomic, write_tables
from occdata.synth.world import Primitives, SceneWorld, make_world
from occdata.visibility import camera_mask, lidar_mask

__all__ = [
    "KEYFRAME_PERIOD_US",
    "TABLE_ONLY_SPLIT",
    "SWEEP_PERIOD_US",
    "LIDAR_AZIMUTH_STEP_DEG",
    "LIDAR_ELEVATIONS_DEG",
    "LIDAR_MAX_RANGE",
    "KeyframeLidar",
    "SensorFrame",
    "SynthConfig",
    "WorldGrid",
    "keyframe_object_boxes",
    "keyframe_times",
    "lidar_returns",
    "render_camera",
    "render_lidar",
    "scene_world",
    "spun_returns",
    "synthesize",
]

KEYFRAME_PERIOD_US = NUSCENES.keyframe_period_us  # 2 Hz
SWEEP_PERIOD_US = NUSCENES.sweep_period_us  # LIDAR_TOP at 20 Hz: 9 sweeps between consecutive keyframes
MASK_SWEEP_RADIUS = 2  # mask_lidar aggregates the sweeps of keyframes k-2 .. k+2 of the scene
CAMERA_MAX_DEPTH = 150.0  # m along the optical axis; beyond is drawn as sky (depth 0)
LIDAR_MAX_RANGE = 80.0  # m
TABLE_VERSION = NUSCENES.version
LIDAR_ELEVATIONS_DEG = np.array(NUSCENES.reference.elevations_deg)  # HDL-32E-like, ring 0 = lowest beam
LIDAR_AZIMUTH_STEP_DEG = NUSCENES.reference.azimuth_step_deg
CELL = 4.0  # m, 2D acceleration grid cell
JPEG_QUALITY = 92
SCENE_SPACING = 3000.0  # m between scene worlds in the global frame
BASE_TIMESTAMP_US = 1_600_000_000_000_000
MAP_NAME = "synth-town"
TABLE_ONLY_SPLIT = "table_only"  # the split of `--table-only-scenes` (build/labels select train, val)
TABLE_ONLY_BOXES = 34  # boxes per keyframe of a table-only scene: nuScenes trainval's mean (1.17 M / 34,149)


@dataclass(frozen=True)
class SynthConfig:
    """Options of `occdata synth`."""

    out: Path
    scenes: int = 2
    samples: int = 10
    seed: int = 0
    width: int | None = None  # None: the rig's native image size (nuscenes 1600x900)
    height: int | None = None
    progress: bool = True
    table_only_scenes: int = 0  # extra scenes written as table rows alone (`_write_table_only_scene`)
    table_only_samples: int = 40  # keyframes per table-only scene (nuScenes: 34,149 / 850 = 40.2)
    grids: tuple[GridSpec, ...] = ()  # more truth grids, gts/<grid>/ in their layouts (occ3d's is always written)
    rig: str = "nuscenes"  # a key of occdata.synth.rig.RIGS
    uncompensated: bool = False  # LiDARs spin over one period, each point at its own time (pcd rigs)
    image_masks: Path | None = None  # also <dir>/<image path>.png: each image's truth class ids (uint8, 255 sky)


@dataclass(frozen=True, eq=False)
class WorldGrid:
    """The world's primitives at one timestamp, binned into the 2D acceleration grid."""

    prims: Primitives
    cell_start: np.ndarray
    items: np.ndarray
    cell_ztop: np.ndarray
    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    z_top: float

    @staticmethod
    def build(world: SceneWorld, t_us: int) -> WorldGrid:
        prims = world.primitives_at(t_us)
        g = world.ground
        nx = int(math.ceil(g.codes.shape[1] * g.cell / CELL))
        ny = int(math.ceil(g.codes.shape[0] * g.cell / CELL))
        cs, items, cell_ztop = render.build_cell_grid(prims.params, g.x0, g.y0, CELL, nx, ny)
        z_top = float(max(prims.params[:, 8].max(initial=0.0), 1.0)) + 0.01
        return WorldGrid(prims, cs, items, cell_ztop, g.x0, g.y0, CELL, nx, ny, z_top)

    def cast(self, origin: np.ndarray, dirs: np.ndarray, t_max: float) -> tuple[np.ndarray, np.ndarray]:
        return render.cast_rays(np.ascontiguousarray(origin, np.float64), np.ascontiguousarray(dirs, np.float64),
                                t_max, self.prims.params, self.cell_start, self.items, self.cell_ztop, self.x0,
                                self.y0, self.cell,
                                self.nx, self.ny, self.z_top)


def ego_transform(world: SceneWorld, t_us: int) -> np.ndarray:
    """`T_global_from_ego (4, 4) float64` at a timestamp (z = 0, yaw only, like nuScenes)."""
    xy, yaw = world.ego.pose_at(t_us)
    c, s = math.cos(float(yaw)), math.sin(float(yaw))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = xy
    return T


def render_camera(
    world: SceneWorld, wg: WorldGrid, T_global_from_cam: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray cast one camera through pixel centres (integer pixel coordinates).

    Returns `rgb (H, W, 3) uint8`, `depth (H, W) float32` (metres along the camera z axis, 0 = sky)
    and `classes (H, W) uint8`, the Occ3D class each pixel sees (`render.SKY_CLASS` 255: sky).
    """
    _, variants = render.palette_tables()
    g = world.ground
    origin = np.ascontiguousarray(T_global_from_cam[:3, 3])
    return render.render_camera_kernel(
        np.linalg.inv(K), np.ascontiguousarray(T_global_from_cam[:3, :3]), origin, width, height, CAMERA_MAX_DEPTH,
        wg.prims.params, wg.cell_start, wg.items, wg.cell_ztop, wg.x0, wg.y0, wg.cell, wg.nx, wg.ny, wg.z_top,
        wg.prims.cls, wg.prims.style, g.codes, g.x0, g.y0, g.cell, variants, render.SUN_DIR)


_REFLECTIVITY = np.array([0.3, 0.8, 0.5, 0.6, 0.6, 0.5, 0.5, 0.35, 0.9, 0.5, 0.55, 0.12, 0.2, 0.25, 0.3, 0.4, 0.28,
                          0.0])


def lidar_directions(spec: LidarSpec = NUSCENES.reference) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions in the lidar frame `(N, 3) float64` (azimuth-major) and ring index `(N,)`."""
    az = np.deg2rad(np.arange(0.0, 360.0, spec.azimuth_step_deg))
    el = np.deg2rad(np.array(spec.elevations_deg))
    A, E = np.meshgrid(az, el, indexing="ij")
    dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    ring = np.broadcast_to(np.arange(len(el)), A.shape).reshape(-1)
    return dirs, ring


def lidar_returns(
    world: SceneWorld, wg: WorldGrid, T_global_from_lidar: np.ndarray, spec: LidarSpec = NUSCENES.reference
) -> tuple[np.ndarray, np.ndarray]:
    """Spin the LiDAR once at one instant; returns the returns `(N, 5) float32`: x, y, z (lidar frame),
    intensity (0-255, class reflectivity x incidence cosine), ring index; and the Occ3D class
    `(N,) int` of the surface each return hit."""
    return _returns(world, wg, T_global_from_lidar, *lidar_directions(spec))[:2]


SPIN_SECTORS = 36  # a spinning LiDAR's turn is cast in this many azimuth sectors, each at its own time


def spun_returns(world: SceneWorld, wg: WorldGrid, T_ego_from_lidar: np.ndarray, t_us: int, spin_us: int,
                 spec: LidarSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`lidar_returns` of a LiDAR turning over `spin_us` centred on `t_us`: azimuth sector m of
    `SPIN_SECTORS` fires at its own time t_m from the ego pose then (actors stay at `t_us`), and its
    points are in the LiDAR frame of t_m, as an uncompensated LiDAR reports them. Returns the points
    `(N, 5) float32`, classes `(N,)`, times `(N,) int64` us, and the truth: points and ray origins
    `(N, 3) float64` in global."""
    dirs, ring = lidar_directions(spec)
    sector = np.minimum((np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2 * np.pi) / (2 * np.pi) * SPIN_SECTORS)
                        .astype(np.int64), SPIN_SECTORS - 1)
    parts = []
    for m in range(SPIN_SECTORS):
        t_m = t_us - spin_us // 2 + (2 * m + 1) * spin_us // (2 * SPIN_SECTORS)
        T_global_from_lidar = ego_transform(world, t_m) @ T_ego_from_lidar
        sel = sector == m
        points, cls, points_global = _returns(world, wg, T_global_from_lidar, dirs[sel], ring[sel])
        parts.append((points, cls, np.full(len(points), t_m, np.int64), points_global,
                      np.broadcast_to(T_global_from_lidar[:3, 3], points_global.shape)))
    return tuple(np.concatenate([p[n] for p in parts]) for n in range(5))  # type: ignore[return-value]


def _returns(world: SceneWorld, wg: WorldGrid, T_global_from_lidar: np.ndarray, dirs_lidar: np.ndarray,
             ring: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The returns of rays `dirs_lidar (N, 3)` (rings `ring (N,)`) from the LiDAR at `T_global_from_lidar`:
    as `lidar_returns`, plus the points in global `(M, 3) float64`."""
    dirs_global = dirs_lidar @ T_global_from_lidar[:3, :3].T
    origin_global = T_global_from_lidar[:3, 3].copy()
    t, hit = wg.cast(origin_global, dirs_global, LIDAR_MAX_RANGE)
    ok = hit != render.HIT_NONE
    t, hit, dirs_lidar, dirs_global, ring = t[ok], hit[ok], dirs_lidar[ok], dirs_global[ok], ring[ok]
    normals_global = render.hit_normals(origin_global, dirs_global, t, hit, wg.prims.params).astype(np.float64)
    points_global = origin_global + t[:, None] * dirs_global
    cls = np.where(hit >= 0, wg.prims.cls[np.maximum(hit, 0)], world.ground.lookup(points_global[:, :2]))
    cos_inc = np.abs((normals_global * dirs_global).sum(axis=1))
    intensity = 255.0 * _REFLECTIVITY[cls] * (0.3 + 0.7 * cos_inc)
    points_lidar = t[:, None] * dirs_lidar  # unit directions: t is the range
    points = np.concatenate([points_lidar, intensity[:, None], ring[:, None]], axis=1).astype(np.float32)
    return points, cls, points_global


def render_lidar(world: SceneWorld, wg: WorldGrid, T_global_from_lidar: np.ndarray,
                 spec: LidarSpec = NUSCENES.reference) -> np.ndarray:
    """The returns `(N, 5) float32` of `lidar_returns`, without their classes."""
    return lidar_returns(world, wg, T_global_from_lidar, spec)[0]


def point_file_bytes(rig: SynthRig, points: np.ndarray, t_us: int, times: np.ndarray | None = None) -> bytes:
    """A sweep's file: raw float32 x 5 (`.pcd.bin`, `.bin`), or a binary PCD with x, y, z, intensity and a
    uint64 `timestamp` per point (TruckScenes' fields): `times (N,)` (a spin, `spun_returns`), else the
    sweep's timestamp for every point (a LiDAR spinning at one instant)."""
    if rig.point_format == "raw5":
        return points.tobytes()
    import io

    import pypcd4

    stamps = np.full(len(points), t_us, np.uint64) if times is None else np.asarray(times, np.uint64)
    cols = [points[:, 0], points[:, 1], points[:, 2], points[:, 3], stamps]
    pc = pypcd4.PointCloud.from_points(cols, ("x", "y", "z", "intensity", "timestamp"),
                                       (np.float32,) * 4 + (np.uint64,))
    buf = io.BytesIO()
    pc.save(buf, encoding=pypcd4.Encoding.BINARY)
    return buf.getvalue()


def _pose_row(token: str, T: np.ndarray, t_us: int) -> dict[str, Any]:
    return {"token": token, "timestamp": int(t_us), "rotation": quaternion_wxyz_from_matrix(T[:3, :3]),
            "translation": [float(T[0, 3]), float(T[1, 3]), 0.0]}


def _n_val(n_scenes: int) -> int:
    return max(1, round(0.2 * n_scenes)) if n_scenes >= 2 else 0


@dataclass(frozen=True, eq=False)
class KeyframeLidar:
    """The written keyframe LIDAR_TOP sweep: `points (N, 5) float32` as in the file, `lidarseg (N,)
    uint8` nuScenes-lidarseg index per point, `T_global_from_lidar (4, 4) float64`."""

    points: np.ndarray
    lidarseg: np.ndarray
    T_global_from_lidar: np.ndarray


@dataclass(frozen=True, eq=False)
class SensorFrame:
    """One written sensor file of a keyframe: channel, timestamp (us), filename (relative to the root),
    `T_global_from_ego (4, 4) float64` at that timestamp."""

    channel: str
    timestamp: int
    filename: str
    T_global_from_ego: np.ndarray


def _render_keyframe(
    out: Path, world: SceneWorld, scene_name: str, t_lidar: int, sd_tokens: dict[str, str], width: int, height: int,
    extra_lidar_times: tuple[int, ...] = (), rig: SynthRig = NUSCENES, masks: Path | None = None,
) -> tuple[list[SensorFrame], dict[str, np.ndarray], KeyframeLidar, _Rays]:
    """Render and write the rig's camera images (+ depth maps) and every LiDAR's sweep of the keyframe
    at `t_lidar` (the reference LiDAR's timestamp); returns the written frames, the Occ3D labels (key
    ego = ego at `t_lidar`), the reference sweep with its per-point lidarseg labels and the rays behind
    the masks (every LiDAR's keyframe sweep). `mask_lidar` also counts the reference LiDAR's returns
    of sweeps at `extra_lidar_times` (not written). `masks`: also each image's class ids under that
    folder (`mask_path`)."""
    T_global_from_keyego = ego_transform(world, t_lidar)
    T_keyego_from_global = invert_rigid(T_global_from_keyego)
    wg_lidar = WorldGrid.build(world, t_lidar)
    semantics = world_semantics(world.ground, wg_lidar.prims, T_global_from_keyego)
    cam_K, cam_T = [], []
    frames = []
    for cam in rig.cameras:
        ch = cam.channel
        ts = t_lidar + cam.time_offset_us
        T_global_from_ego = ego_transform(world, ts)
        T_global_from_sensor = T_global_from_ego @ cam.calib.T_ego_from_sensor
        rel = rig.sensor_file(scene_name, ch, ts, key=True)
        K = cam.K(width, height)
        # Actors are placed at the camera's own timestamp.
        rgb, depth, classes = render_camera(world, WorldGrid.build(world, ts), T_global_from_sensor, K, width,
                                            height)
        ok, jpg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise OccDataError(f"JPEG encoding failed for {rel}")
        write_atomic(out / rel, jpg.tobytes())
        if masks is not None:
            ok, png = cv2.imencode(".png", classes)
            if not ok:
                raise OccDataError(f"PNG encoding failed for the mask of {rel}")
            write_atomic(mask_path(masks, rel), png.tobytes())
        write_atomic(out / "depth" / f"{sd_tokens[ch]}.npy", _npy_bytes(depth))
        cam_K.append(K)
        cam_T.append(invert_rigid(T_keyego_from_global @ T_global_from_sensor))
        frames.append(SensorFrame(ch, int(ts), rel, T_global_from_ego))
    origins, ends = [], []
    for n, lidar in enumerate(rig.lidars):
        ch = lidar.channel
        ts = t_lidar + lidar.time_offset_us
        T_global_from_ego = ego_transform(world, ts)
        T_global_from_sensor = T_global_from_ego @ lidar.calib.T_ego_from_sensor
        rel = rig.sensor_file(scene_name, ch, ts, key=True)
        wg = wg_lidar if ts == t_lidar else WorldGrid.build(world, ts)
        T_keyego_from_lidar = T_keyego_from_global @ T_global_from_sensor
        if rig.spin_us:  # the truth's rays from where each sector's points were taken
            points, cls, times, ends_global, origins_global = spun_returns(
                world, wg, lidar.calib.T_ego_from_sensor, ts, rig.spin_us, lidar)
            write_atomic(out / rel, point_file_bytes(rig, points, ts, times))
            origins.append(transform_points(T_keyego_from_global, origins_global))
            ends.append(transform_points(T_keyego_from_global, ends_global))
        else:
            points, cls = lidar_returns(world, wg, T_global_from_sensor, lidar)
            write_atomic(out / rel, point_file_bytes(rig, points, ts))
            origins.append(np.broadcast_to(T_keyego_from_lidar[:3, 3], (len(points), 3)))
            ends.append(transform_points(T_keyego_from_lidar, points[:, :3]))
        if n == 0:
            key_lidar = KeyframeLidar(points, LIDARSEG_FROM_OCC3D[cls], T_global_from_sensor)
            # Like Occ3D, aggregate neighbouring sweeps (their returns only: a ray's free space is
            # stale once actors have moved) so ground beyond one sweep's rings is observed too.
            T_ego_from_lidar = lidar.calib.T_ego_from_sensor
            for t_other in extra_lidar_times:
                T_keyego_from_other = T_keyego_from_global @ ego_transform(world, t_other) @ T_ego_from_lidar
                other = render_lidar(world, WorldGrid.build(world, t_other),
                                     ego_transform(world, t_other) @ T_ego_from_lidar, lidar)
                p_keyego = transform_points(T_keyego_from_other, other[:, :3])
                origins.append(p_keyego)
                ends.append(p_keyego)
        frames.append(SensorFrame(ch, int(ts), rel, T_global_from_ego))
    rays = _Rays(np.concatenate(origins), np.concatenate(ends), np.stack(cam_K), np.stack(cam_T),
                 np.array([[width, height]] * len(cam_K)))
    return frames, _masked(semantics, rays, GRID), key_lidar, rays


@dataclass(frozen=True)
class _Rays:
    """What a keyframe's masks are made of, in key ego: the LiDAR rays `origins`, `ends` `(N, 3)
    float64`, and the cameras `K (C, 3, 3)`, `T_cam_from_keyego (C, 4, 4)`, `image_size (C, 2)`."""

    origins: np.ndarray
    ends: np.ndarray
    K: np.ndarray
    T_cam_from_keyego: np.ndarray
    image_size: np.ndarray


def _masked(semantics: np.ndarray, rays: _Rays, grid: OccGrid) -> dict[str, np.ndarray]:
    """Occ3D-style labels of a key-ego grid: the semantics with the LiDAR mask of the rays and the
    camera mask, which lies within it (docs/design.md#visibility-masks, docs/visibility.md)."""
    lower = np.asarray(grid.lower, np.float64)
    mask_lidar = lidar_mask(semantics, rays.origins, rays.ends, lower, grid.voxel_size)
    mask_camera = camera_mask(semantics, mask_lidar, rays.K, rays.T_cam_from_keyego, rays.image_size, lower,
                              grid.voxel_size)
    return {"semantics": semantics, "mask_lidar": mask_lidar, "mask_camera": mask_camera}


def _grid_truth(world: SceneWorld, t_lidar: int, rays: _Rays, spec: GridSpec,
                rig: SynthRig = NUSCENES) -> dict[str, np.ndarray]:
    """The keyframe's truth on `spec`, in its frame (key ego, or the reference LiDAR at `t_lidar`);
    masks for the layouts that have them (key-ego grids only)."""
    T_global_from_grid = ego_transform(world, t_lidar)
    if spec.frame is LabelFrame.LIDAR:
        T_global_from_grid = T_global_from_grid @ rig.reference.calib.T_ego_from_sensor
    semantics = grid_semantics(world.ground, world.primitives_at(t_lidar), T_global_from_grid, spec.grid)
    if spec.masks and spec.frame is LabelFrame.KEY_EGO:
        return _masked(semantics, rays, spec.grid)
    return {"semantics": semantics}


def _lidarseg_row(sd_token: str, version: str = TABLE_VERSION) -> dict[str, str]:
    return {"token": sd_token, "sample_data_token": sd_token,
            "filename": f"lidarseg/{version}/{sd_token}_lidarseg.bin"}


def _write_lidarseg(out: Path, sd_token: str, key_lidar: KeyframeLidar, version: str) -> dict[str, str]:
    """Write `lidarseg/<version>/<sd_token>_lidarseg.bin` (uint8, one label per point in file order);
    returns its lidarseg.json row."""
    row = _lidarseg_row(sd_token, version)
    write_atomic(out / row["filename"], key_lidar.lidarseg.astype(np.uint8).tobytes())
    return row


def _annotate(world: SceneWorld, t_lidar: int, key_lidar: KeyframeLidar,
              spec: LidarSpec = NUSCENES.reference) -> KeyframeAnnotation:
    """Boxes of the keyframe at `t_lidar` with the counts of the reference LiDAR's written (float32)
    returns in them."""
    T = key_lidar.T_global_from_lidar
    points_global = transform_points(T, key_lidar.points[:, :3].astype(np.float64))
    dirs_global = lidar_directions(spec)[0] @ T[:3, :3].T
    return annotate_keyframe(world, t_lidar, points_global, T[:3, 3].copy(), dirs_global, LIDAR_MAX_RANGE)


def _scene_t0(scene_index: int) -> int:
    return BASE_TIMESTAMP_US + scene_index * 3_600_000_000


def scene_world(seed: int, scene_index: int, n_samples: int) -> SceneWorld:
    """The world of scene `scene_index` written by `occdata synth --seed seed --samples n_samples`
    (independent of the number of scenes, of the image size and of the rig)."""
    rng = np.random.default_rng([seed, scene_index])
    return make_world(rng, (1000.0 + SCENE_SPACING * scene_index, 1000.0), _scene_t0(scene_index), n_samples)


def keyframe_times(scene_index: int, n_samples: int, period_us: int = KEYFRAME_PERIOD_US) -> list[int]:
    """Reference LiDAR (= sample) timestamps in microseconds of the scene's keyframes."""
    return [_scene_t0(scene_index) + 100_000 + k * period_us for k in range(n_samples)]


def keyframe_object_boxes(seed: int, scene_index: int, n_samples: int, k: int) -> ObjectBoxes:
    """The boxes of all box-annotated objects at keyframe k of a scene of `occdata synth --seed seed
    --samples n_samples`, in that keyframe's key-ego frame (the Occ3D grid's frame), with their
    speeds (`ObjectBoxes.moving`). Same boxes as the scene's sample_annotation rows."""
    world = scene_world(seed, scene_index, n_samples)
    t_us = keyframe_times(scene_index, n_samples)[k]
    return object_boxes(world, t_us).to_frame(invert_rigid(ego_transform(world, t_us)))


def _write_sweep(out: Path, world: SceneWorld, scene_name: str, t_us: int, rig: SynthRig, lidar: LidarSpec
                 ) -> SensorFrame:
    """Render and write one non-keyframe sweep of `lidar` (actors at `t_us`) under sweeps/."""
    T_global_from_ego = ego_transform(world, t_us)
    rel = rig.sensor_file(scene_name, lidar.channel, t_us, key=False)
    if rig.spin_us:
        points, _, times, _, _ = spun_returns(world, WorldGrid.build(world, t_us), lidar.calib.T_ego_from_sensor, t_us,
                                              rig.spin_us, lidar)
        write_atomic(out / rel, point_file_bytes(rig, points, t_us, times))
        return SensorFrame(lidar.channel, int(t_us), rel, T_global_from_ego)
    points = render_lidar(world, WorldGrid.build(world, t_us), T_global_from_ego @ lidar.calib.T_ego_from_sensor,
                          lidar)
    write_atomic(out / rel, point_file_bytes(rig, points, t_us))
    return SensorFrame(lidar.channel, int(t_us), rel, T_global_from_ego)


def _sweep_row(token: str, sample_token: str, cs_token: str, f: SensorFrame, link: tuple[str, str],
               fileformat: str = "pcd") -> dict[str, Any]:
    """The sample_data row of a non-keyframe LiDAR sweep (`link`: prev, next in the LiDAR chain)."""
    return {"token": token, "sample_token": sample_token, "ego_pose_token": token, "calibrated_sensor_token": cs_token,
            "timestamp": f.timestamp, "fileformat": fileformat, "is_key_frame": False, "height": 0, "width": 0,
            "filename": f.filename, "prev": link[0], "next": link[1]}


def _lidar_chain(seed: int, si: int, n_samples: int, key_times: list[int], channel: str = LIDAR_CHANNEL,
                 rig: SynthRig = NUSCENES, offset_us: int = 0) -> list[tuple[str, int, int]]:
    """One LiDAR's sample_data of the scene in time order as (token, timestamp, keyframe index k): the
    sweeps between keyframes k-1 and k belong to sample k (as nuScenes assigns them), j = n..1
    (nuScenes: 9 at 20 Hz; TruckScenes: 4 at 10 Hz; Lyft: none, every row a keyframe)."""
    chain = []
    for k in range(n_samples):
        if k > 0:
            chain += [(make_token(seed, "sample_data", si, k, channel, "sweep", j),
                       key_times[k] + offset_us - j * rig.sweep_period_us, k)
                      for j in range(rig.sweeps_between, 0, -1)]
        chain.append((make_token(seed, "sample_data", si, k, channel), key_times[k] + offset_us, k))
    return chain


def _calibrated_sensor_rows(
    seed: int, scene_index: int, sensor_tok: dict[str, str], width: int, height: int, rig: SynthRig = NUSCENES
) -> dict[str, dict[str, Any]]:
    """One calibrated_sensor row per channel (cameras, then LiDARs) of a scene: the rig."""
    rows = {}
    for cal, K in [(c.calib, c.K(width, height).tolist()) for c in rig.cameras] + [(x.calib, []) for x in rig.lidars]:
        rows[cal.channel] = {"token": make_token(seed, "calibrated_sensor", scene_index, cal.channel),
                             "sensor_token": sensor_tok[cal.channel], "translation": list(cal.translation),
                             "rotation": list(cal.rotation_wxyz), "camera_intrinsic": K}
    return rows


@dataclass(frozen=True)
class _Scene:
    """What the keyframes of one scene share while they are written."""

    out: Path
    world: Any
    name: str
    samples: int
    width: int
    height: int
    sample_toks: list[str]
    sd_toks: dict[str, list[str]]
    cs_tok: dict[str, str]
    key_times: list[int]
    lidar_chains: dict[str, list[tuple[str, int, int]]]
    link: dict[str, tuple[str, str]]
    grids: tuple[GridSpec, ...] = ()
    rig: SynthRig = NUSCENES
    masks: Path | None = None


def _keyframe_sample_data(sc: _Scene, f: Any, k: int) -> dict[str, Any]:
    """The sample_data row of keyframe `k`'s frame `f` (a camera image or a keyframe LiDAR sweep)."""
    tok = sc.sd_toks[f.channel][k]
    is_cam = f.channel not in sc.lidar_chains
    return {
        "token": tok, "sample_token": sc.sample_toks[k],
        "ego_pose_token": tok,  # one ego pose per sample_data, as in nuScenes
        "calibrated_sensor_token": sc.cs_tok[f.channel], "timestamp": f.timestamp,
        "fileformat": sc.rig.camera_fileformat if is_cam else sc.rig.lidar_fileformat, "is_key_frame": True,
        "height": sc.height if is_cam else 0, "width": sc.width if is_cam else 0, "filename": f.filename,
        "prev": sc.link[tok][0] if not is_cam else sc.sd_toks[f.channel][k - 1] if k > 0 else "",
        "next": sc.link[tok][1] if not is_cam else sc.sd_toks[f.channel][k + 1] if k + 1 < sc.samples else "",
    }


def _sample_row(sc: _Scene, k: int, scene_tok: str) -> dict[str, Any]:
    return {"token": sc.sample_toks[k], "timestamp": sc.key_times[k], "scene_token": scene_tok,
            "prev": sc.sample_toks[k - 1] if k > 0 else "", "next": sc.sample_toks[k + 1] if k + 1 < sc.samples else ""}


def _add_sensor_rows(sc: _Scene, tables: dict[str, list], k: int, frames: list[SensorFrame],
                     sweeps: list[tuple[str, SensorFrame]]) -> None:
    """The ego_pose and sample_data rows of keyframe `k`'s sweeps (token, frame), then of its frames."""
    for tok, f in sweeps:
        tables["ego_pose"].append(_pose_row(tok, f.T_global_from_ego, f.timestamp))
        tables["sample_data"].append(_sweep_row(tok, sc.sample_toks[k], sc.cs_tok[f.channel], f, sc.link[tok],
                                                sc.rig.lidar_fileformat))
    for f in frames:
        tables["ego_pose"].append(_pose_row(sc.sd_toks[f.channel][k], f.T_global_from_ego, f.timestamp))
        tables["sample_data"].append(_keyframe_sample_data(sc, f, k))


def _write_keyframe(sc: _Scene, tables: dict[str, list], k: int, scene_tok: str) -> KeyframeAnnotation:
    """Render keyframe `k` and the sweeps before it, write their files and labels, add their rows."""
    rig = sc.rig
    t_lidar, s_tok, ref = sc.key_times[k], sc.sample_toks[k], rig.reference.channel
    tables["sample"].append(_sample_row(sc, k, scene_tok))
    window = range(max(0, k - MASK_SWEEP_RADIUS), min(sc.samples, k + MASK_SWEEP_RADIUS + 1))
    near = [sc.key_times[j] for j in window if j != k]
    frames, labels, key_lidar, rays = _render_keyframe(sc.out, sc.world, sc.name, t_lidar,
                                                       {ch: toks[k] for ch, toks in sc.sd_toks.items()}, sc.width,
                                                       sc.height, tuple(near), rig, sc.masks)
    if rig.lidarseg:
        tables["lidarseg"].append(_write_lidarseg(sc.out, sc.sd_toks[ref][k], key_lidar, rig.version))
    annotation = _annotate(sc.world, t_lidar, key_lidar, rig.reference)
    sweeps = [(tok, _write_sweep(sc.out, sc.world, sc.name, t, rig, lidar)) for lidar in rig.lidars
              for tok, t, kk in sc.lidar_chains[lidar.channel] if kk == k and tok != sc.sd_toks[lidar.channel][k]]
    _add_sensor_rows(sc, tables, k, frames, sweeps)
    write_label(label_path(sc.out / "gts", sc.name, s_tok), labels)
    lidar_file = Path(next(f.filename for f in frames if f.channel == ref)).name
    site = LabelSite(sc.name, scene_tok, s_tok, sc.sd_toks[ref][k], lidar_file)
    for spec in sc.grids:
        write_grid_label(spec, sc.out / "gts" / spec.name, site, _grid_truth(sc.world, t_lidar, rays, spec, rig))
    return annotation


def _begin_scene(config: SynthConfig, si: int, tables: dict[str, list], sensor_tok: dict[str, str], split: str,
                 world: SceneWorld | None, rig: SynthRig, width: int, height: int) -> tuple[_Scene, str]:
    """Scene `si`'s log, calibration and scene rows; the tokens and links its keyframes share, and its token."""
    seed = config.seed
    channels = [c.channel for c in rig.cameras] + [x.channel for x in rig.lidars]
    log_tok = make_token(seed, "log", si)
    tables["log"].append({"token": log_tok, "logfile": f"synth-s{seed}-{si:04d}", "vehicle": "synth",
                          "date_captured": "2020-09-13", "location": MAP_NAME})
    cs_rows = _calibrated_sensor_rows(seed, si, sensor_tok, width, height, rig)
    tables["calibrated_sensor"] += cs_rows.values()
    scene_tok = make_token(seed, "scene", si)
    sample_toks = [make_token(seed, "sample", si, k) for k in range(config.samples)]
    what = "Synthetic town drive" if world is not None else "Table rows without sensor files"
    tables["scene"].append({
        "token": scene_tok, "log_token": log_tok, "nbr_samples": config.samples, "name": f"synth-{si:04d}",
        "description": f"{what}, seed {seed}; split={split}",
        "first_sample_token": sample_toks[0], "last_sample_token": sample_toks[-1],
    })
    key_times = keyframe_times(si, config.samples, rig.keyframe_period_us)
    chains = {x.channel: _lidar_chain(seed, si, config.samples, key_times, x.channel, rig, x.time_offset_us)
              for x in rig.lidars}
    link = {tok: (chain[n - 1][0] if n else "", chain[n + 1][0] if n + 1 < len(chain) else "")
            for chain in chains.values() for n, (tok, _, _) in enumerate(chain)}
    sc = _Scene(
        out=Path(config.out), world=world, name=f"synth-{si:04d}",
        samples=config.samples, width=width, height=height, sample_toks=sample_toks,
        sd_toks={ch: [make_token(seed, "sample_data", si, k, ch) for k in range(config.samples)] for ch in channels},
        cs_tok={ch: row["token"] for ch, row in cs_rows.items()}, key_times=key_times, lidar_chains=chains, link=link,
        grids=tuple(g for g in config.grids if g.name != "occ3d"),  # occ3d's truth is gts/ itself
        rig=rig, masks=config.image_masks,
    )
    return sc, scene_tok


def _ego_motion_rows(world: SceneWorld, poses: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """TruckScenes' ego_motion rows, one per ego pose row (token and timestamp shared): velocity and
    acceleration in the vehicle frame, yaw and yaw rate, from the ego path by central differences
    (h = 10 ms); pitch, roll and their rates 0 (the synthetic ego drives on flat ground)."""
    h = 10_000

    def state(t: int) -> tuple[np.ndarray, float]:
        xy, yaw = world.ego.pose_at(t)
        return np.asarray(xy, np.float64), float(yaw)

    rows = []
    for row in poses:
        t = int(row["timestamp"])
        (p0, y0), (p1, y1), (p2, y2) = state(t - h), state(t), state(t + h)
        c, s = np.cos(y1), np.sin(y1)
        R_t = np.array([[c, s], [-s, c]])  # global -> vehicle (yaw only)
        v = R_t @ ((p2 - p0) / (2e-6 * h))
        a = R_t @ ((p2 - 2 * p1 + p0) / (1e-6 * h) ** 2)
        yaw_rate = float(np.angle(np.exp(1j * (y2 - y0)))) / (2e-6 * h)
        rows.append({"token": row["token"], "timestamp": t, "vx": float(v[0]), "vy": float(v[1]), "vz": 0.0,
                     "ax": float(a[0]), "ay": float(a[1]), "az": 0.0, "yaw": y1, "pitch": 0.0, "roll": 0.0,
                     "yaw_rate": yaw_rate, "pitch_rate": 0.0, "roll_rate": 0.0})
    return rows


def _write_scene(config: SynthConfig, si: int, tables: dict[str, list], sensor_tok: dict[str, str],
                 n_val: int, bar: tqdm, rig: SynthRig = NUSCENES, size: tuple[int, int] = (1600, 900)) -> None:
    """Scene `si`: its log, calibrations, scene row, then every keyframe; then its boxes."""
    split = "val" if si >= config.scenes - n_val else "train"
    world = scene_world(config.seed, si, config.samples)
    sc, scene_tok = _begin_scene(config, si, tables, sensor_tok, split, world, rig, *size)
    first_pose = len(tables["ego_pose"])
    keyframe_anns: list[KeyframeAnnotation] = []
    for k in range(config.samples):
        keyframe_anns.append(_write_keyframe(sc, tables, k, scene_tok))
        bar.update(1)
    instances, annotations = annotation_rows(config.seed, si, sc.sample_toks, keyframe_anns)
    tables["instance"] += instances
    tables["sample_annotation"] += annotations
    if rig.ego_motion:
        motion = _ego_motion_rows(world, tables["ego_pose"][first_pose:])
        tables["ego_motion_cabin"] += motion  # no cabin suspension here: the cabin moves as the chassis
        tables["ego_motion_chassis"] += [dict(r) for r in motion]


def _write_table_only_scene(config: SynthConfig, si: int, tables: dict[str, list], sensor_tok: dict[str, str],
                            rig: SynthRig = NUSCENES, size: tuple[int, int] = (1600, 900)) -> None:
    """Scene `si` as table rows alone, with no file (image, LiDAR, lidarseg, label, depth) behind them:
    the rows a reader keeps of a nuScenes-size tree, made in milliseconds (`--table-only-scenes`).
    Per keyframe as a rendered scene: 7 keyframe and 9 sweep sample_data rows with their ego poses,
    a lidarseg row, and `TABLE_ONLY_BOXES` boxes (parked cars; the ego drives straight at 5 m/s)."""
    config = dataclasses.replace(config, samples=config.table_only_samples)
    sc, scene_tok = _begin_scene(config, si, tables, sensor_tok, TABLE_ONLY_SPLIT, None, rig, *size)
    x0 = 1000.0 + SCENE_SPACING * si

    def pose(t_us: int) -> np.ndarray:
        T = np.eye(4)
        T[:2, 3] = (x0 + 5.0 * (t_us - sc.key_times[0]) / 1e6, 1000.0)
        return T

    for k, t_lidar in enumerate(sc.key_times):
        tables["sample"].append(_sample_row(sc, k, scene_tok))
        times = {c.channel: t_lidar + c.time_offset_us for c in (*rig.cameras, *rig.lidars)}
        frames = [SensorFrame(ch, t, rig.sensor_file(sc.name, ch, t, key=True), pose(t)) for ch, t in times.items()]
        sweeps = [(tok, SensorFrame(lidar.channel, t, rig.sensor_file(sc.name, lidar.channel, t, key=False), pose(t)))
                  for lidar in rig.lidars for tok, t, kk in sc.lidar_chains[lidar.channel]
                  if kk == k and tok != sc.sd_toks[lidar.channel][k]]
        _add_sensor_rows(sc, tables, k, frames, sweeps)
        if rig.lidarseg:
            tables["lidarseg"].append(_lidarseg_row(sc.sd_toks[rig.reference.channel][k], rig.version))
    n = TABLE_ONLY_BOXES
    centers = np.stack([x0 + 8.0 * np.arange(n), np.full(n, 1006.0), np.full(n, 0.85)], axis=1)
    boxes = ObjectBoxes(tuple(f"static-{i}" for i in range(n)), ("car",) * n, centers,
                        np.tile([1.9, 4.6, 1.7], (n, 1)), np.zeros(n), np.zeros(n))
    keyframe = KeyframeAnnotation(boxes, np.zeros(n, np.int64), np.full(n, 4, np.int64))
    instances, annotations = annotation_rows(config.seed, si, sc.sample_toks, [keyframe] * config.samples)
    tables["instance"] += instances
    tables["sample_annotation"] += annotations


def _apply_table_quirks(rig: SynthRig, tables: dict[str, list]) -> None:
    """The rig's table quirks, applied to the finished rows: TruckScenes' UTM-like global x, y (ego
    poses and boxes moved together), Lyft's float microseconds (+0.25 us, which float64 holds exactly
    at 1.6e15 and which rounds back to the integer) and NaN width/height on its LiDAR rows."""
    dx, dy = rig.global_offset
    if dx or dy:
        for row in (*tables["ego_pose"], *tables["sample_annotation"]):
            row["translation"] = [row["translation"][0] + dx, row["translation"][1] + dy, row["translation"][2]]
    if rig.float_timestamps:
        for name in ("sample", "sample_data", "ego_pose"):
            for row in tables[name]:
                row["timestamp"] = float(row["timestamp"]) + 0.25
    if rig.nan_lidar_size:
        for row in tables["sample_data"]:
            if row["fileformat"] == rig.lidar_fileformat:
                row["width"] = row["height"] = float("nan")


def synthesize(config: SynthConfig) -> Path:
    """Generate the world and write the tree under `config.out`; returns the output directory.

    Layout (nuscenes rig): `v1.0-mini/*.json` (13 tables + lidarseg), `samples/CAM_*/*.jpg`,
    `samples/LIDAR_TOP/*.pcd.bin`, `lidarseg/v1.0-mini/<sd_token>_lidarseg.bin` (keyframe LIDAR_TOP
    point labels), `sweeps/LIDAR_TOP/*.pcd.bin` (20 Hz LiDAR between keyframes; cameras are
    keyframe-only), `gts/<scene>/<sample_token>/labels.npz` (Occ3D), `depth/<sample_data_token>.npy`,
    `maps/`. Other rigs (`SynthRig`): their folders, formats and tables, the same gts/ and depth/.
    """
    if config.rig not in RIGS:
        raise OccDataError(f"--rig {config.rig!r}: not one of {', '.join(RIGS)}")
    rig = RIGS[config.rig]
    if config.uncompensated:
        if rig.point_format != "pcd":
            raise OccDataError(f"--uncompensated needs per-point times: the {rig.name} rig writes no .pcd files "
                               "(use --rig truckscenes)")
        rig = dataclasses.replace(rig, spin_us=rig.sweep_period_us)
    width, height = config.width or rig.native_size[0], config.height or rig.native_size[1]
    if config.scenes < 1 or config.samples < 1:
        raise OccDataError("--scenes and --samples must be >= 1")
    if config.table_only_scenes < 0 or config.table_only_samples < 1:
        raise OccDataError("--table-only-scenes must be >= 0 and --table-only-samples >= 1")
    if width < 16 or height < 16:
        raise OccDataError("--width and --height must be >= 16")
    out = Path(config.out)
    tables = static_tables(config.seed, rig)
    sensor_tok = {r["channel"]: r["token"] for r in tables["sensor"]}
    for name in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "log", "lidarseg",
                 *(("ego_motion_cabin", "ego_motion_chassis") if rig.ego_motion else ())):
        tables[name] = []
    n_val = _n_val(config.scenes)
    with tqdm(total=config.scenes * config.samples, desc="synth", unit="sample", disable=not config.progress) as bar:
        for si in range(config.scenes):
            _write_scene(config, si, tables, sensor_tok, n_val, bar, rig, (width, height))
    for si in range(config.scenes, config.scenes + config.table_only_scenes):
        _write_table_only_scene(config, si, tables, sensor_tok, rig, (width, height))
    if "map" in rig.tables:
        log_tokens = [r["token"] for r in tables["log"]]
        tables["map"] = [{"token": make_token(config.seed, "map", MAP_NAME), "log_tokens": log_tokens,
                          "category": "semantic_prior", "filename": f"maps/{MAP_NAME}.png"}]
        ok, png = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
        write_atomic(out / "maps" / f"{MAP_NAME}.png", png.tobytes())
    if not rig.lidarseg:
        del tables["lidarseg"]
    _apply_table_quirks(rig, tables)
    write_tables(out / rig.version, tables, rig.tables)
    return out


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()
