"""Load a nuScenes-format version folder into frozen keyframe records (DESIGN §3).

Only what occupancy needs is kept: keyframe samples with their 6 cameras and LIDAR_TOP sweep, each
sensor with its calibration and its own ego pose. Every foreign key is resolved here, so a broken
tree fails early with one line naming the table and token.
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from occdata.constants import CAMERA_ORDER, LIDAR_CHANNEL
from occdata.errors import OccDataError
from occdata.nuscenes.records import CameraRecord, LidarRecord, NuScenesDataset, SampleRecord, SceneRecord
from occdata.nuscenes.splits import official_split
from occdata.nuscenes.tables import load_table

__all__ = ["SPLIT_TAG", "find_version", "load_lidar_points", "load_nuscenes", "validate_sample"]

# Non-official scenes (synthetic or custom data) may carry "split=<name>" in their description.
SPLIT_TAG = re.compile(r"\bsplit=([A-Za-z0-9_]+)")
_NEEDED_TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor", "log")
_CHANNELS = frozenset((*CAMERA_ORDER, LIDAR_CHANNEL))


def find_version(root: Path, version: str | None) -> str:
    """The version folder to read: `version` if given, else the only `v*` folder holding scene.json."""
    root = Path(root)
    if not root.is_dir():
        raise OccDataError(f"dataset root not found: {root}")
    found = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "scene.json").is_file())
    if version is not None:
        if not (root / version).is_dir():
            raise OccDataError(
                f"version folder not found: {root / version} (present: {', '.join(found) or 'none'})"
            )
        return version
    if len(found) != 1:
        raise OccDataError(
            f"cannot choose a version folder under {root}: found {found or 'none'}; pass --version"
        )
    return found[0]


def _get(row: dict[str, Any], key: str, table: str) -> Any:
    try:
        return row[key]
    except KeyError:
        raise OccDataError(f"{table}.json: row {row.get('token', '?')!r} has no field {key!r}") from None


def _ref(rows: dict[str, dict[str, Any]], token: str, table: str, src: str) -> dict[str, Any]:
    try:
        return rows[token]
    except (KeyError, TypeError):
        raise OccDataError(f"dangling token: {src} refers to {table} {token!r}, not in {table}.json") from None


def _rotation(q_wxyz: Any) -> np.ndarray:
    """Rotation matrix of a quaternion. Rounding in the files is normalised away; a quaternion far
    from unit length is kept as is, so `validate_sample` reports a non-orthonormal rotation."""
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(-1)
    if q.shape != (4,):
        return np.full((3, 3), np.nan)
    n = np.linalg.norm(q)
    if np.isfinite(n) and abs(n - 1.0) < 1e-3:
        q = q / n
    w, x, y, z = q
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def _pose(row: dict[str, Any], table: str) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rotation(_get(row, "rotation", table))
    t = np.asarray(_get(row, "translation", table), dtype=np.float64).reshape(-1)
    T[:3, 3] = t if t.shape == (3,) else np.nan
    return T


def load_nuscenes(root: Path | str, version: str | None = None, check_files: bool = False) -> NuScenesDataset:
    """Read `<root>/<version>/*.json` into keyframe records.

    Scenes come in table order, samples per scene in time order (following `next` links from
    `first_sample_token`). Each scene gets a split: the official one for nuScenes scene names
    (mini_train/mini_val for v1.0-mini), else a `split=NAME` tag in its description, else
    "unassigned". With `check_files`, every keyframe sensor file must exist.
    Raises `OccDataError` (one line, naming the file or token) on a broken tree.
    """
    root = Path(root).resolve()
    version = find_version(root, version)
    vdir = root / version
    for name in _NEEDED_TABLES:
        if not (vdir / f"{name}.json").is_file():
            raise OccDataError(f"missing table: {vdir / f'{name}.json'}")

    sensors = load_table(vdir / "sensor.json")
    calibs = load_table(vdir / "calibrated_sensor.json")
    logs = load_table(vdir / "log.json")
    scenes_raw = load_table(vdir / "scene.json")
    samples_raw = load_table(vdir / "sample.json")

    channel_of_calib: dict[str, str] = {}
    for tok, cs in calibs.items():
        sensor = _ref(sensors, _get(cs, "sensor_token", "calibrated_sensor"), "sensor", f"calibrated_sensor {tok!r}")
        channel_of_calib[tok] = _get(sensor, "channel", "sensor")

    def keep_sd(row: dict[str, Any]) -> bool:
        if not row.get("is_key_frame", False):
            return False
        cs_tok = _get(row, "calibrated_sensor_token", "sample_data")
        if cs_tok not in channel_of_calib:
            _ref(calibs, cs_tok, "calibrated_sensor", f"sample_data {row.get('token')!r}")
        return channel_of_calib[cs_tok] in _CHANNELS

    sample_data = load_table(vdir / "sample_data.json", keep=keep_sd)
    pose_tokens = {_get(sd, "ego_pose_token", "sample_data") for sd in sample_data.values()}
    ego_poses = load_table(vdir / "ego_pose.json", keep=lambda r: r.get("token") in pose_tokens)

    by_sample: dict[str, dict[str, dict[str, Any]]] = defaultdict(dict)
    for tok, sd in sample_data.items():
        s_tok = _get(sd, "sample_token", "sample_data")
        _ref(samples_raw, s_tok, "sample", f"sample_data {tok!r}")
        channel = channel_of_calib[sd["calibrated_sensor_token"]]
        if channel in by_sample[s_tok]:
            raise OccDataError(f"sample {s_tok!r} has two keyframe {channel} records in sample_data.json")
        by_sample[s_tok][channel] = sd

    def abs_path(sd: dict[str, Any]) -> Path:
        path = root / _get(sd, "filename", "sample_data")
        if check_files and not path.is_file():
            raise OccDataError(f"missing sensor file: {path} (sample_data {sd['token']!r})")
        return path

    def pose_of(sd: dict[str, Any]) -> np.ndarray:
        src = f"sample_data {sd['token']!r}"
        return _pose(_ref(ego_poses, sd["ego_pose_token"], "ego_pose", src), "ego_pose")

    def make_sample(s_tok: str, scene_name: str, index: int) -> SampleRecord:
        row = samples_raw[s_tok]
        sds = by_sample.get(s_tok, {})
        missing = [c for c in (*CAMERA_ORDER, LIDAR_CHANNEL) if c not in sds]
        if missing:
            raise OccDataError(f"sample {s_tok!r} has no keyframe sample_data for {', '.join(missing)}")
        cams = []
        for channel in CAMERA_ORDER:
            sd = sds[channel]
            cs = calibs[sd["calibrated_sensor_token"]]
            K = np.asarray(_get(cs, "camera_intrinsic", "calibrated_sensor"), dtype=np.float64)
            if K.shape != (3, 3):
                raise OccDataError(f"calibrated_sensor {cs['token']!r} ({channel}): camera_intrinsic is not 3x3")
            cams.append(
                CameraRecord(
                    channel=channel,
                    token=sd["token"],
                    path=abs_path(sd),
                    K=K,
                    T_ego_from_cam=_pose(cs, "calibrated_sensor"),
                    T_global_from_ego=pose_of(sd),
                    timestamp=int(_get(sd, "timestamp", "sample_data")),
                    width=int(_get(sd, "width", "sample_data")),
                    height=int(_get(sd, "height", "sample_data")),
                )
            )
        sd = sds[LIDAR_CHANNEL]
        lidar = LidarRecord(
            channel=LIDAR_CHANNEL,
            token=sd["token"],
            path=abs_path(sd),
            T_ego_from_lidar=_pose(calibs[sd["calibrated_sensor_token"]], "calibrated_sensor"),
            T_global_from_ego=pose_of(sd),
            timestamp=int(_get(sd, "timestamp", "sample_data")),
        )
        return SampleRecord(
            token=s_tok,
            scene_token=_get(row, "scene_token", "sample"),
            scene_name=scene_name,
            index_in_scene=index,
            timestamp=int(_get(row, "timestamp", "sample")),
            prev=row.get("prev", ""),
            next=row.get("next", ""),
            cameras=tuple(cams),
            lidar=lidar,
        )

    scenes: list[SceneRecord] = []
    samples: list[SampleRecord] = []
    for sc_tok, sc in scenes_raw.items():
        name = _get(sc, "name", "scene")
        log = _ref(logs, _get(sc, "log_token", "scene"), "log", f"scene {name!r}")
        tok = _get(sc, "first_sample_token", "scene")
        chain: list[str] = []
        while tok:
            row = _ref(samples_raw, tok, "sample", f"scene {name!r}" if not chain else f"sample {chain[-1]!r}.next")
            if row.get("scene_token") != sc_tok:
                raise OccDataError(f"sample {tok!r} is linked from scene {name!r} but belongs to another scene")
            if len(chain) > len(samples_raw):
                raise OccDataError(f"scene {name!r}: the sample next-links form a cycle")
            chain.append(tok)
            tok = row.get("next", "")
        last = _get(sc, "last_sample_token", "scene")
        if chain and chain[-1] != last:
            raise OccDataError(f"scene {name!r}: the next-links end at {chain[-1]!r}, not last_sample_token {last!r}")
        description = str(sc.get("description", ""))
        split = official_split(name, version)
        if split is None:
            tag = SPLIT_TAG.search(description)
            split = tag.group(1) if tag else "unassigned"
        scenes.append(
            SceneRecord(
                token=sc_tok,
                name=name,
                description=description,
                log_token=sc["log_token"],
                location=str(log.get("location", "")),
                split=split,
                sample_tokens=tuple(chain),
            )
        )
        samples.extend(make_sample(t, name, i) for i, t in enumerate(chain))
    return NuScenesDataset(root=root, version=version, scenes=tuple(scenes), samples=tuple(samples))


def load_lidar_points(path: Path | str) -> np.ndarray:
    """A `.pcd.bin` sweep: `(N, 5) float32` x, y, z, intensity, ring (lidar frame)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise OccDataError(f"missing sensor file: {path}") from None
    if len(raw) == 0 or len(raw) % 20:
        raise OccDataError(f"corrupt LiDAR file {path}: {len(raw)} bytes is not a positive multiple of 20")
    points = np.frombuffer(raw, dtype=np.float32).reshape(-1, 5)
    if not np.isfinite(points[:, :3]).all():
        raise OccDataError(f"corrupt LiDAR file {path}: non-finite coordinates")
    return points


def validate_sample(sample: SampleRecord) -> None:
    """Raise `OccDataError` if any calibration or pose of the sample is non-finite or not rigid."""

    def check_rigid(T: np.ndarray, what: str) -> None:
        if not np.isfinite(T).all():
            raise OccDataError(f"sample {sample.token!r}: {what} has NaN/inf values")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise OccDataError(f"sample {sample.token!r}: {what} rotation is not orthonormal")

    for cam in sample.cameras:
        check_rigid(cam.T_ego_from_cam, f"{cam.channel} calibration")
        check_rigid(cam.T_global_from_ego, f"{cam.channel} ego pose")
        K = cam.K
        if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise OccDataError(f"sample {sample.token!r}: {cam.channel} intrinsics are invalid")
    check_rigid(sample.lidar.T_ego_from_lidar, "LIDAR_TOP calibration")
    check_rigid(sample.lidar.T_global_from_ego, "LIDAR_TOP ego pose")
