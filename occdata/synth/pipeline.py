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

from occdata.constants import CAMERA_ORDER, GRID, LIDAR_CHANNEL, OccGrid
from occdata.errors import OccDataError
from occdata.formats.gridfiles import LabelSite, write_grid_label
from occdata.formats.gridspec import GridSpec, LabelFrame
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
from occdata.synth.rig import CAMERA_TIME_OFFSETS_US, RIG, camera_K
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
    "synthesize",
]

KEYFRAME_PERIOD_US = 500_000  # 2 Hz
SWEEP_PERIOD_US = 50_000  # LIDAR_TOP at 20 Hz: 9 sweeps between consecutive keyframes
MASK_SWEEP_RADIUS = 2  # mask_lidar aggregates the sweeps of keyframes k-2 .. k+2 of the scene
CAMERA_MAX_DEPTH = 150.0  # m along the optical axis; beyond is drawn as sky (depth 0)
LIDAR_MAX_RANGE = 80.0  # m
TABLE_VERSION = "v1.0-mini"
LIDAR_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)  # HDL-32E-like, ring 0 = lowest beam
LIDAR_AZIMUTH_STEP_DEG = 0.33
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
    width: int = 1600
    height: int = 900
    progress: bool = True
    table_only_scenes: int = 0  # extra scenes written as table rows alone (`_write_table_only_scene`)
    table_only_samples: int = 40  # keyframes per table-only scene (nuScenes: 34,149 / 850 = 40.2)
    grids: tuple[GridSpec, ...] = ()  # more truth grids, gts/<grid>/ in their layouts (occ3d's is always written)


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
) -> tuple[np.ndarray, np.ndarray]:
    """Ray cast one camera through pixel centres (integer pixel coordinates).

    Returns `rgb (H, W, 3) uint8` and `depth (H, W) float32` (metres along the camera z axis, 0 = sky).
    """
    _, variants = render.palette_tables()
    g = world.ground
    origin = np.ascontiguousarray(T_global_from_cam[:3, 3])
    rgb, depth = render.render_camera_kernel(
        np.linalg.inv(K), np.ascontiguousarray(T_global_from_cam[:3, :3]), origin, width, height, CAMERA_MAX_DEPTH,
        wg.prims.params, wg.cell_start, wg.items, wg.cell_ztop, wg.x0, wg.y0, wg.cell, wg.nx, wg.ny, wg.z_top,
        wg.prims.cls, wg.prims.style, g.codes, g.x0, g.y0, g.cell, variants, render.SUN_DIR)
    return rgb, depth


_REFLECTIVITY = np.array([0.3, 0.8, 0.5, 0.6, 0.6, 0.5, 0.5, 0.35, 0.9, 0.5, 0.55, 0.12, 0.2, 0.25, 0.3, 0.4, 0.28,
                          0.0])


def lidar_directions() -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions in the lidar frame `(N, 3) float64` (azimuth-major) and ring index `(N,)`."""
    az = np.deg2rad(np.arange(0.0, 360.0, LIDAR_AZIMUTH_STEP_DEG))
    el = np.deg2rad(LIDAR_ELEVATIONS_DEG)
    A, E = np.meshgrid(az, el, indexing="ij")
    dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    ring = np.broadcast_to(np.arange(len(el)), A.shape).reshape(-1)
    return dirs, ring


def lidar_returns(
    world: SceneWorld, wg: WorldGrid, T_global_from_lidar: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Spin the LiDAR once at one instant; returns the returns `(N, 5) float32`: x, y, z (lidar frame),
    intensity (0-255, class reflectivity x incidence cosine), ring index; and the Occ3D class
    `(N,) int` of the surface each return hit."""
    dirs_lidar, ring = lidar_directions()
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
    return np.concatenate([points_lidar, intensity[:, None], ring[:, None]], axis=1).astype(np.float32), cls


def render_lidar(world: SceneWorld, wg: WorldGrid, T_global_from_lidar: np.ndarray) -> np.ndarray:
    """The returns `(N, 5) float32` of `lidar_returns`, without their classes."""
    return lidar_returns(world, wg, T_global_from_lidar)[0]


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
    extra_lidar_times: tuple[int, ...] = (),
) -> tuple[list[SensorFrame], dict[str, np.ndarray], KeyframeLidar, _Rays]:
    """Render and write the 6 camera images (+ depth maps) and the LiDAR sweep of the keyframe at
    `t_lidar`; returns the written frames, the Occ3D labels (key ego = ego at `t_lidar`), the
    LiDAR sweep with its per-point lidarseg labels and the rays behind the masks.
    `mask_lidar` also counts the returns of sweeps at `extra_lidar_times` (not written)."""
    T_global_from_keyego = ego_transform(world, t_lidar)
    T_keyego_from_global = invert_rigid(T_global_from_keyego)
    wg_lidar = WorldGrid.build(world, t_lidar)
    semantics = world_semantics(world.ground, wg_lidar.prims, T_global_from_keyego)
    cam_K, cam_T = [], []
    frames = []
    for ch in (*CAMERA_ORDER, LIDAR_CHANNEL):
        is_cam = ch != LIDAR_CHANNEL
        ts = t_lidar + (CAMERA_TIME_OFFSETS_US[ch] if is_cam else 0)
        T_global_from_ego = ego_transform(world, ts)
        T_global_from_sensor = T_global_from_ego @ RIG[ch].T_ego_from_sensor
        rel = _sample_file(scene_name, ch, ts)
        if is_cam:
            K = camera_K(ch, width, height)
            # Actors are placed at the camera's own timestamp.
            rgb, depth = render_camera(world, WorldGrid.build(world, ts), T_global_from_sensor, K, width, height)
            ok, jpg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise OccDataError(f"JPEG encoding failed for {rel}")
            write_atomic(out / rel, jpg.tobytes())
            write_atomic(out / "depth" / f"{sd_tokens[ch]}.npy", _npy_bytes(depth))
            cam_K.append(K)
            cam_T.append(invert_rigid(T_keyego_from_global @ T_global_from_sensor))
        else:
            points, cls = lidar_returns(world, wg_lidar, T_global_from_sensor)
            key_lidar = KeyframeLidar(points, LIDARSEG_FROM_OCC3D[cls], T_global_from_sensor)
            write_atomic(out / rel, points.tobytes())
            T_keyego_from_lidar = T_keyego_from_global @ T_global_from_sensor
            origins = [np.broadcast_to(T_keyego_from_lidar[:3, 3], (len(points), 3))]
            ends = [transform_points(T_keyego_from_lidar, points[:, :3])]
            # Like Occ3D, aggregate neighbouring sweeps (their returns only: a ray's free space is
            # stale once actors have moved) so ground beyond one sweep's rings is observed too.
            for t_other in extra_lidar_times:
                T_keyego_from_other = T_keyego_from_global @ ego_transform(world, t_other) @ RIG[ch].T_ego_from_sensor
                other = render_lidar(world, WorldGrid.build(world, t_other),
                                     ego_transform(world, t_other) @ RIG[ch].T_ego_from_sensor)
                p_keyego = transform_points(T_keyego_from_other, other[:, :3])
                origins.append(p_keyego)
                ends.append(p_keyego)
            rays = _Rays(np.concatenate(origins), np.concatenate(ends), np.stack(cam_K), np.stack(cam_T),
                         np.array([[width, height]] * len(cam_K)))
        frames.append(SensorFrame(ch, int(ts), rel, T_global_from_ego))
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
    camera mask, which lies within it (DESIGN §5.3, docs/visibility.md)."""
    lower = np.asarray(grid.lower, np.float64)
    mask_lidar = lidar_mask(semantics, rays.origins, rays.ends, lower, grid.voxel_size)
    mask_camera = camera_mask(semantics, mask_lidar, rays.K, rays.T_cam_from_keyego, rays.image_size, lower,
                              grid.voxel_size)
    return {"semantics": semantics, "mask_lidar": mask_lidar, "mask_camera": mask_camera}


def _grid_truth(world: SceneWorld, t_lidar: int, rays: _Rays, spec: GridSpec) -> dict[str, np.ndarray]:
    """The keyframe's truth on `spec`, in its frame (key ego, or LIDAR_TOP at `t_lidar`); masks for
    the layouts that have them (key-ego grids only)."""
    T_global_from_grid = ego_transform(world, t_lidar)
    if spec.frame is LabelFrame.LIDAR:
        T_global_from_grid = T_global_from_grid @ RIG[LIDAR_CHANNEL].T_ego_from_sensor
    semantics = grid_semantics(world.ground, world.primitives_at(t_lidar), T_global_from_grid, spec.grid)
    if spec.masks and spec.frame is LabelFrame.KEY_EGO:
        return _masked(semantics, rays, spec.grid)
    return {"semantics": semantics}


def _sample_file(scene_name: str, channel: str, t_us: int) -> str:
    return f"samples/{channel}/{scene_name}__{channel}__{t_us}.{'jpg' if channel != LIDAR_CHANNEL else 'pcd.bin'}"


def _sweep_file(scene_name: str, t_us: int) -> str:
    return f"sweeps/{LIDAR_CHANNEL}/{scene_name}__{LIDAR_CHANNEL}__{t_us}.pcd.bin"


def _lidarseg_row(sd_token: str) -> dict[str, str]:
    return {"token": sd_token, "sample_data_token": sd_token,
            "filename": f"lidarseg/{TABLE_VERSION}/{sd_token}_lidarseg.bin"}


def _write_lidarseg(out: Path, sd_token: str, key_lidar: KeyframeLidar) -> dict[str, str]:
    """Write `lidarseg/<version>/<sd_token>_lidarseg.bin` (uint8, one label per point in file order);
    returns its lidarseg.json row."""
    row = _lidarseg_row(sd_token)
    write_atomic(out / row["filename"], key_lidar.lidarseg.astype(np.uint8).tobytes())
    return row


def _annotate(world: SceneWorld, t_lidar: int, key_lidar: KeyframeLidar) -> KeyframeAnnotation:
    """Boxes of the keyframe at `t_lidar` with the counts of the written (float32) returns in them."""
    T = key_lidar.T_global_from_lidar
    points_global = transform_points(T, key_lidar.points[:, :3].astype(np.float64))
    dirs_global = lidar_directions()[0] @ T[:3, :3].T
    return annotate_keyframe(world, t_lidar, points_global, T[:3, 3].copy(), dirs_global, LIDAR_MAX_RANGE)


def _scene_t0(scene_index: int) -> int:
    return BASE_TIMESTAMP_US + scene_index * 3_600_000_000


def scene_world(seed: int, scene_index: int, n_samples: int) -> SceneWorld:
    """The world of scene `scene_index` written by `occdata synth --seed seed --samples n_samples`
    (independent of the number of scenes and of the image size)."""
    rng = np.random.default_rng([seed, scene_index])
    return make_world(rng, (1000.0 + SCENE_SPACING * scene_index, 1000.0), _scene_t0(scene_index), n_samples)


def keyframe_times(scene_index: int, n_samples: int) -> list[int]:
    """LIDAR_TOP (= sample) timestamps in microseconds of the scene's keyframes."""
    return [_scene_t0(scene_index) + 100_000 + k * KEYFRAME_PERIOD_US for k in range(n_samples)]


def keyframe_object_boxes(seed: int, scene_index: int, n_samples: int, k: int) -> ObjectBoxes:
    """The boxes of all box-annotated objects at keyframe k of a scene of `occdata synth --seed seed
    --samples n_samples`, in that keyframe's key-ego frame (the Occ3D grid's frame), with their
    speeds (`ObjectBoxes.moving`). Same boxes as the scene's sample_annotation rows."""
    world = scene_world(seed, scene_index, n_samples)
    t_us = keyframe_times(scene_index, n_samples)[k]
    return object_boxes(world, t_us).to_frame(invert_rigid(ego_transform(world, t_us)))


def _write_sweep(out: Path, world: SceneWorld, scene_name: str, t_us: int) -> SensorFrame:
    """Render and write one non-keyframe LIDAR_TOP sweep (actors at `t_us`) under sweeps/."""
    T_global_from_ego = ego_transform(world, t_us)
    points = render_lidar(world, WorldGrid.build(world, t_us), T_global_from_ego @ RIG[LIDAR_CHANNEL].T_ego_from_sensor)
    rel = _sweep_file(scene_name, t_us)
    write_atomic(out / rel, points.tobytes())
    return SensorFrame(LIDAR_CHANNEL, int(t_us), rel, T_global_from_ego)


def _sweep_row(token: str, sample_token: str, cs_token: str, f: SensorFrame, link: tuple[str, str]) -> dict[str, Any]:
    """The sample_data row of a non-keyframe LIDAR_TOP sweep (`link`: prev, next in the LiDAR chain)."""
    return {"token": token, "sample_token": sample_token, "ego_pose_token": token, "calibrated_sensor_token": cs_token,
            "timestamp": f.timestamp, "fileformat": "pcd", "is_key_frame": False, "height": 0, "width": 0,
            "filename": f.filename, "prev": link[0], "next": link[1]}


def _lidar_chain(seed: int, si: int, n_samples: int, key_times: list[int]) -> list[tuple[str, int, int]]:
    """The scene's LIDAR_TOP sample_data in time order as (token, timestamp, keyframe index k): the
    sweeps between keyframes k-1 and k belong to sample k (as nuScenes assigns them), j = 9..1."""
    n_between = KEYFRAME_PERIOD_US // SWEEP_PERIOD_US - 1
    chain = []
    for k in range(n_samples):
        if k > 0:
            chain += [(make_token(seed, "sample_data", si, k, LIDAR_CHANNEL, "sweep", j),
                       key_times[k] - j * SWEEP_PERIOD_US, k) for j in range(n_between, 0, -1)]
        chain.append((make_token(seed, "sample_data", si, k, LIDAR_CHANNEL), key_times[k], k))
    return chain


def _calibrated_sensor_rows(
    seed: int, scene_index: int, sensor_tok: dict[str, str], width: int, height: int
) -> dict[str, dict[str, Any]]:
    """One calibrated_sensor row per channel (cameras, then LIDAR_TOP) of a scene: the rig."""
    rows = {}
    for ch in (*CAMERA_ORDER, LIDAR_CHANNEL):
        cal = RIG[ch]
        K = camera_K(ch, width, height).tolist() if cal.intrinsic is not None else []
        rows[ch] = {"token": make_token(seed, "calibrated_sensor", scene_index, ch), "sensor_token": sensor_tok[ch],
                    "translation": list(cal.translation), "rotation": list(cal.rotation_wxyz),
                    "camera_intrinsic": K}
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
    lidar_chain: list[tuple[str, int, int]]
    link: dict[str, tuple[str, str]]
    grids: tuple[GridSpec, ...] = ()


def _keyframe_sample_data(sc: _Scene, f: Any, k: int) -> dict[str, Any]:
    """The sample_data row of keyframe `k`'s frame `f` (a camera image or the keyframe LiDAR sweep)."""
    tok = sc.sd_toks[f.channel][k]
    is_cam = f.channel != LIDAR_CHANNEL
    return {
        "token": tok, "sample_token": sc.sample_toks[k],
        "ego_pose_token": tok,  # one ego pose per sample_data, as in nuScenes
        "calibrated_sensor_token": sc.cs_tok[f.channel], "timestamp": f.timestamp,
        "fileformat": "jpg" if is_cam else "pcd", "is_key_frame": True,
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
        tables["sample_data"].append(_sweep_row(tok, sc.sample_toks[k], sc.cs_tok[LIDAR_CHANNEL], f, sc.link[tok]))
    for f in frames:
        tables["ego_pose"].append(_pose_row(sc.sd_toks[f.channel][k], f.T_global_from_ego, f.timestamp))
        tables["sample_data"].append(_keyframe_sample_data(sc, f, k))


def _write_keyframe(sc: _Scene, tables: dict[str, list], k: int, scene_tok: str) -> KeyframeAnnotation:
    """Render keyframe `k` and the sweeps before it, write their files and labels, add their rows."""
    channels = (*CAMERA_ORDER, LIDAR_CHANNEL)
    t_lidar, s_tok = sc.key_times[k], sc.sample_toks[k]
    tables["sample"].append(_sample_row(sc, k, scene_tok))
    window = range(max(0, k - MASK_SWEEP_RADIUS), min(sc.samples, k + MASK_SWEEP_RADIUS + 1))
    near = [sc.key_times[j] for j in window if j != k]
    frames, labels, key_lidar, rays = _render_keyframe(sc.out, sc.world, sc.name, t_lidar,
                                                       {ch: sc.sd_toks[ch][k] for ch in channels}, sc.width,
                                                       sc.height, tuple(near))
    tables["lidarseg"].append(_write_lidarseg(sc.out, sc.sd_toks[LIDAR_CHANNEL][k], key_lidar))
    annotation = _annotate(sc.world, t_lidar, key_lidar)
    sweeps = [(tok, _write_sweep(sc.out, sc.world, sc.name, t)) for tok, t, kk in sc.lidar_chain
              if kk == k and t != t_lidar]
    _add_sensor_rows(sc, tables, k, frames, sweeps)
    write_label(label_path(sc.out / "gts", sc.name, s_tok), labels)
    lidar_file = Path(next(f.filename for f in frames if f.channel == LIDAR_CHANNEL)).name
    site = LabelSite(sc.name, scene_tok, s_tok, sc.sd_toks[LIDAR_CHANNEL][k], lidar_file)
    for spec in sc.grids:
        write_grid_label(spec, sc.out / "gts" / spec.name, site, _grid_truth(sc.world, t_lidar, rays, spec))
    return annotation


def _begin_scene(config: SynthConfig, si: int, tables: dict[str, list], sensor_tok: dict[str, str], split: str,
                 world: SceneWorld | None) -> tuple[_Scene, str]:
    """Scene `si`'s log, calibration and scene rows; the tokens and links its keyframes share, and its token."""
    seed, channels = config.seed, (*CAMERA_ORDER, LIDAR_CHANNEL)
    log_tok = make_token(seed, "log", si)
    tables["log"].append({"token": log_tok, "logfile": f"synth-s{seed}-{si:04d}", "vehicle": "synth",
                          "date_captured": "2020-09-13", "location": MAP_NAME})
    cs_rows = _calibrated_sensor_rows(seed, si, sensor_tok, config.width, config.height)
    tables["calibrated_sensor"] += cs_rows.values()
    scene_tok = make_token(seed, "scene", si)
    sample_toks = [make_token(seed, "sample", si, k) for k in range(config.samples)]
    what = "Synthetic town drive" if world is not None else "Table rows without sensor files"
    tables["scene"].append({
        "token": scene_tok, "log_token": log_tok, "nbr_samples": config.samples, "name": f"synth-{si:04d}",
        "description": f"{what}, seed {seed}; split={split}",
        "first_sample_token": sample_toks[0], "last_sample_token": sample_toks[-1],
    })
    key_times = keyframe_times(si, config.samples)
    chain = _lidar_chain(seed, si, config.samples, key_times)
    sc = _Scene(
        out=Path(config.out), world=world, name=f"synth-{si:04d}",
        samples=config.samples, width=config.width, height=config.height, sample_toks=sample_toks,
        sd_toks={ch: [make_token(seed, "sample_data", si, k, ch) for k in range(config.samples)] for ch in channels},
        cs_tok={ch: row["token"] for ch, row in cs_rows.items()}, key_times=key_times, lidar_chain=chain,
        link={tok: (chain[n - 1][0] if n else "", chain[n + 1][0] if n + 1 < len(chain) else "")
              for n, (tok, _, _) in enumerate(chain)},
        grids=tuple(g for g in config.grids if g.name != "occ3d"),  # occ3d's truth is gts/ itself
    )
    return sc, scene_tok


def _write_scene(config: SynthConfig, si: int, tables: dict[str, list], sensor_tok: dict[str, str],
                 n_val: int, bar: tqdm) -> None:
    """Scene `si`: its log, calibrations, scene row, then every keyframe; then its boxes."""
    split = "val" if si >= config.scenes - n_val else "train"
    sc, scene_tok = _begin_scene(config, si, tables, sensor_tok, split, scene_world(config.seed, si, config.samples))
    keyframe_anns: list[KeyframeAnnotation] = []
    for k in range(config.samples):
        keyframe_anns.append(_write_keyframe(sc, tables, k, scene_tok))
        bar.update(1)
    instances, annotations = annotation_rows(config.seed, si, sc.sample_toks, keyframe_anns)
    tables["instance"] += instances
    tables["sample_annotation"] += annotations


def _write_table_only_scene(config: SynthConfig, si: int, tables: dict[str, list], sensor_tok: dict[str, str]) -> None:
    """Scene `si` as table rows alone, with no file (image, LiDAR, lidarseg, label, depth) behind them:
    the rows a reader keeps of a nuScenes-size tree, made in milliseconds (`--table-only-scenes`).
    Per keyframe as a rendered scene: 7 keyframe and 9 sweep sample_data rows with their ego poses,
    a lidarseg row, and `TABLE_ONLY_BOXES` boxes (parked cars; the ego drives straight at 5 m/s)."""
    config = dataclasses.replace(config, samples=config.table_only_samples)
    sc, scene_tok = _begin_scene(config, si, tables, sensor_tok, TABLE_ONLY_SPLIT, None)
    x0 = 1000.0 + SCENE_SPACING * si

    def pose(t_us: int) -> np.ndarray:
        T = np.eye(4)
        T[:2, 3] = (x0 + 5.0 * (t_us - sc.key_times[0]) / 1e6, 1000.0)
        return T

    for k, t_lidar in enumerate(sc.key_times):
        tables["sample"].append(_sample_row(sc, k, scene_tok))
        times = {ch: t_lidar + CAMERA_TIME_OFFSETS_US.get(ch, 0) for ch in (*CAMERA_ORDER, LIDAR_CHANNEL)}
        frames = [SensorFrame(ch, t, _sample_file(sc.name, ch, t), pose(t)) for ch, t in times.items()]
        sweeps = [(tok, SensorFrame(LIDAR_CHANNEL, t, _sweep_file(sc.name, t), pose(t)))
                  for tok, t, kk in sc.lidar_chain if kk == k and t != t_lidar]
        _add_sensor_rows(sc, tables, k, frames, sweeps)
        tables["lidarseg"].append(_lidarseg_row(sc.sd_toks[LIDAR_CHANNEL][k]))
    n = TABLE_ONLY_BOXES
    centers = np.stack([x0 + 8.0 * np.arange(n), np.full(n, 1006.0), np.full(n, 0.85)], axis=1)
    boxes = ObjectBoxes(tuple(f"static-{i}" for i in range(n)), ("car",) * n, centers,
                        np.tile([1.9, 4.6, 1.7], (n, 1)), np.zeros(n), np.zeros(n))
    keyframe = KeyframeAnnotation(boxes, np.zeros(n, np.int64), np.full(n, 4, np.int64))
    instances, annotations = annotation_rows(config.seed, si, sc.sample_toks, [keyframe] * config.samples)
    tables["instance"] += instances
    tables["sample_annotation"] += annotations


def synthesize(config: SynthConfig) -> Path:
    """Generate the world and write the tree under `config.out`; returns the output directory.

    Layout: `v1.0-mini/*.json` (13 tables + lidarseg), `samples/CAM_*/*.jpg`, `samples/LIDAR_TOP/*.pcd.bin`,
    `lidarseg/v1.0-mini/<sd_token>_lidarseg.bin` (keyframe LIDAR_TOP point labels),
    `sweeps/LIDAR_TOP/*.pcd.bin` (20 Hz LiDAR between keyframes; cameras are keyframe-only),
    `gts/<scene>/<sample_token>/labels.npz` (Occ3D), `depth/<sample_data_token>.npy`, `maps/`.
    """
    if config.scenes < 1 or config.samples < 1:
        raise OccDataError("--scenes and --samples must be >= 1")
    if config.table_only_scenes < 0 or config.table_only_samples < 1:
        raise OccDataError("--table-only-scenes must be >= 0 and --table-only-samples >= 1")
    if config.width < 16 or config.height < 16:
        raise OccDataError("--width and --height must be >= 16")
    out = Path(config.out)
    tables = static_tables(config.seed)
    sensor_tok = {r["channel"]: r["token"] for r in tables["sensor"]}
    for name in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "log", "lidarseg"):
        tables[name] = []
    n_val = _n_val(config.scenes)
    with tqdm(total=config.scenes * config.samples, desc="synth", unit="sample", disable=not config.progress) as bar:
        for si in range(config.scenes):
            _write_scene(config, si, tables, sensor_tok, n_val, bar)
    for si in range(config.scenes, config.scenes + config.table_only_scenes):
        _write_table_only_scene(config, si, tables, sensor_tok)
    log_tokens = [r["token"] for r in tables["log"]]
    tables["map"] = [{"token": make_token(config.seed, "map", MAP_NAME), "log_tokens": log_tokens,
                      "category": "semantic_prior", "filename": f"maps/{MAP_NAME}.png"}]
    ok, png = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    write_atomic(out / "maps" / f"{MAP_NAME}.png", png.tobytes())
    write_tables(out / TABLE_VERSION, tables)
    return out


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()
