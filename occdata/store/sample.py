"""Everything one sample contributes to the store, computed from its raw files (runs in workers).

Pure with respect to the store: reads the sample's files, returns arrays. Bad input raises
`SampleError` with the file and the reason; the builder records or re-raises it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from occdata.errors import OccDataError
from occdata.formats.gridfiles import IGNORE, read_grid_label, to_occ3d_ids
from occdata.formats.gridspec import GridSpec, LabelLayout
from occdata.formats.occ3d import OPENOCC_V2, label_keys, read_label, read_openocc_v2_label
from occdata.nuscenes import LidarRecord, SampleRecord, load_lidar_points, validate_sample
from occdata.sensors.jpeg_check import decode_jpeg_checked
from occdata.sensors.projection import project_to_cameras
from occdata.store.bev import bev_bits
from occdata.store.layout import MIN_TOKEN_BYTES, N_PREV, token_bytes

__all__ = ["MAX_LIDAR_SWEEPS", "SampleError", "SampleOptions", "SampleResult", "depth_points", "jpeg_size",
           "process_sample"]

MAX_LIDAR_SWEEPS = 100  # 5 s of 20 Hz sweeps; more would mostly smear moving objects


class SampleError(OccDataError):
    """A problem with one sample's input; the message names the file and the reason."""


@dataclass(frozen=True)
class SampleOptions:
    image_scale: float = 1.0  # 1.0 keeps the original JPEG bytes untouched
    jpeg_quality: int = 90  # only used when re-encoding (image_scale != 1)
    min_depth: float = 0.0  # LiDAR depth targets keep depth > min_depth
    lidar_sweeps: int = 0  # depth targets from the keyframe sweep plus up to this many previous sweeps

    def __post_init__(self) -> None:
        if not 0 <= self.lidar_sweeps <= MAX_LIDAR_SWEEPS:
            raise OccDataError(f"--lidar-sweeps must be in [0, {MAX_LIDAR_SWEEPS}], got {self.lidar_sweeps}")


@dataclass(frozen=True, eq=False)
class SampleResult:
    """Per-sample arrays (no sample axis) plus ragged payloads; `error` set when the sample failed."""

    index: int
    token: str
    arrays: dict[str, np.ndarray]
    jpeg: tuple[bytes, ...]
    uvd: tuple[np.ndarray, ...]  # per camera (M_c, 3) float32
    error: str | None = None


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOF marker, or None if the stream is not a well-formed JPEG."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        seg_len = int.from_bytes(data[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > len(data):
                return None
            return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(data[i + 5 : i + 7], "big")
        i += 2 + seg_len
    return None


def _read_jpeg(path: Path, width: int, height: int, options: SampleOptions) -> bytes:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SampleError(f"missing image file: {path}") from None
    except OSError as exc:  # a folder, a symlink loop, no permission, an I/O error
        raise SampleError(f"cannot read image file {path}: {exc.strerror or exc}") from None
    size = jpeg_size(data)
    if size is None or not data.rstrip(b"\0").endswith(b"\xff\xd9"):
        raise SampleError(f"corrupt JPEG {path}: not a complete JPEG stream")
    if size != (width, height):
        raise SampleError(f"corrupt JPEG {path}: {size[0]}x{size[1]} but sample_data says {width}x{height}")
    buf = np.frombuffer(data, dtype=np.uint8)
    # A 1/8-scale decode still walks the whole entropy-coded stream: cheap full validation. Any
    # libjpeg warning (damaged data it papered over with grey) rejects the image.
    flag = cv2.IMREAD_REDUCED_GRAYSCALE_8 if options.image_scale == 1.0 else cv2.IMREAD_COLOR
    img, warning = decode_jpeg_checked(buf, flag)
    if img is None or warning:
        raise SampleError(f"corrupt JPEG {path}: {warning or 'decoder rejected the data'}")
    if options.image_scale == 1.0:
        return data
    new_size = (round(width * options.image_scale), round(height * options.image_scale))
    img = cv2.resize(img, new_size, interpolation=cv2.INTER_AREA)
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality])
    if not ok:
        raise SampleError(f"cannot re-encode {path}")
    return enc.tobytes()


def static_arrays(
    sample: SampleRecord,
    scene_index: int,
    split_code: int,
    prev_index: np.ndarray,
    prev_valid: np.ndarray,
    token_width: int = MIN_TOKEN_BYTES,
) -> dict[str, np.ndarray]:
    """Tokens (`token_width` bytes each), calibration, poses and temporal indices: cheap, valid
    even for failed samples."""
    cams = sample.cameras
    rig = sample.camera_rig()
    w = token_width
    return {
        "sample/token": token_bytes(sample.token, w),
        "sample/scene_index": np.int32(scene_index),
        "sample/split": np.uint8(split_code),
        "sample/index_in_scene": np.int32(sample.index_in_scene),
        "sample/timestamp": np.int64(sample.timestamp),
        "sample/lidar_token": token_bytes(sample.lidar.token, w),
        "cam/token": np.stack([token_bytes(c.token, w) for c in cams]),
        "cam/timestamp": np.array([c.timestamp for c in cams], dtype=np.int64),
        "cam/image_size": rig.image_size.astype(np.int32),
        "calib/K": rig.K,
        "calib/T_ego_from_cam": np.stack([c.T_ego_from_cam for c in cams]),
        "calib/T_keyego_from_cam": rig.T_keyego_from_cam,
        "calib/T_ego_from_lidar": sample.lidar.T_ego_from_lidar,
        "pose/T_global_from_keyego": sample.T_global_from_keyego,
        "pose/T_global_from_ego_cam": np.stack([c.T_global_from_ego for c in cams]),
        "temporal/prev_index": prev_index.astype(np.int32),
        "temporal/prev_valid": prev_valid.astype(bool),
    }


def process_sample(
    index: int,
    sample: SampleRecord,
    static: dict[str, np.ndarray],
    label_path: Path | None,
    options: SampleOptions,
    sweeps: tuple[LidarRecord, ...] = (),
    label_format: str = "occ3d",
    grid: GridSpec | None = None,
) -> SampleResult:
    """Read and convert one sample; the depth targets also take the points of `sweeps` (previous
    sweeps of each LiDAR, `NuScenesDataset.lidar_histories`). `label_format` "openocc-v2": the labels file
    is OpenOcc v2's (mapped to our ids, its flow kept as `labels/flow`). `grid`: the labels file is of
    this (non-Occ3D) grid, in its layout and ids (`occdata.formats.gridfiles`; mapped to ours). Bad input gives
    a result with `error` set (never raises it)."""
    try:
        validate_sample(sample)
        jpeg = tuple(_read_jpeg(c.path, c.width, c.height, options) for c in sample.cameras)
        uvd = depth_points(sample, sweeps, static["calib/K"], static["cam/image_size"], options.min_depth)
        arrays = dict(static)
        if label_path is not None and os.path.lexists(label_path):
            labels = _read_labels(label_path, label_format) if grid is None else _read_grid(label_path, grid)
            arrays["labels/present"] = np.bool_(True)
            arrays["labels/semantics"] = labels["semantics"]
            arrays["labels/mask_lidar"] = labels["mask_lidar"]
            arrays["labels/mask_camera"] = labels["mask_camera"]
            arrays["labels/bev"] = bev_bits(labels["semantics"])
            if "flow" in labels:
                arrays["labels/flow"] = labels["flow"]
        else:
            arrays["labels/present"] = np.bool_(False)
        return SampleResult(index=index, token=sample.token, arrays=arrays, jpeg=jpeg, uvd=uvd)
    except OccDataError as exc:  # SampleError, or a calibration rejected by validate_sample
        return SampleResult(index=index, token=sample.token, arrays=dict(static), jpeg=(), uvd=(), error=str(exc))
    except Exception as exc:  # noqa: BLE001 - anything else about this sample's input stays with it
        reason = f"unexpected {type(exc).__name__}: {exc}"
        return SampleResult(index=index, token=sample.token, arrays=dict(static), jpeg=(), uvd=(), error=reason)


def _read_labels(path: Path, label_format: str) -> dict[str, np.ndarray]:
    """The sample's labels in the tree's format; a file of the other format is one `SampleError`."""
    keys = label_keys(path)
    if keys is not None and ("flow" in keys) != (label_format == OPENOCC_V2):
        has, tree = ("has", "Occ3D files (no flow)") if "flow" in keys else ("has no", "OpenOcc v2 files (with flow)")
        raise SampleError(f"labels file {path} {has} 'flow', but the --gts tree's first labels file made this "
                          f"build read {tree}: the tree mixes the two formats (their class ids differ too); "
                          "give --gts a tree of one format")
    return read_openocc_v2_label(path) if label_format == OPENOCC_V2 else read_label(path)


def _read_grid(path: Path, spec: GridSpec) -> dict[str, np.ndarray]:
    """A label file of `spec` -> `semantics` in our ids and the two masks, each `(X, Y, Z) uint8` of the
    grid's shape; a grid without masks gets all-ones masks (attrs["grid"]["mask"] says so)."""
    raw = read_grid_label(spec, path)
    sem = raw["semantics"]
    bad = sem >= len(spec.class_names)
    if spec.layout in (LabelLayout.SURROUNDOCC, LabelLayout.OPENOCCUPANCY):
        bad &= sem != IGNORE  # the sparse readers' noise
    if sem.dtype.kind not in "biu" or bad.any():  # an unknown id must not become free silently
        raise SampleError(f"bad {spec.name} label {path}: {int(bad.sum())} voxels with ids outside the grid's "
                          f"0..{len(spec.class_names) - 1} (max {int(sem.max())})")
    out = {"semantics": to_occ3d_ids(spec, sem)}
    for k in ("mask_lidar", "mask_camera"):
        m = raw.get(k) if spec.masks else np.ones(spec.shape, np.uint8)
        if m is None or m.shape != spec.shape or m.dtype.kind not in "biu" or (m.size and m.max() > 1):
            raise SampleError(f"bad {spec.name} label {path}: {k} missing, not of shape {spec.shape} or not 0/1")
        out[k] = m.astype(np.uint8, copy=False)
    return out


def depth_points(
    sample: SampleRecord, sweeps: tuple[LidarRecord, ...], K: np.ndarray, image_size: np.ndarray, min_depth: float
) -> tuple[np.ndarray, ...]:
    """Per camera `(M_c, 3) float32` (u, v, depth): the keyframe sweep's points of every LiDAR (rig
    order, the reference first), then each of `sweeps` in order, projected into the ORIGINAL image
    through lidar(t_i) -> ego(t_i) -> global -> ego(t_cam) -> camera -> K (each sweep's own pose and
    calibration: the car's motion is compensated exactly).
    K `(C, 3, 3) float64`; image_size `(C, 2)` (W, H). Raises `OccDataError` for a missing or corrupt
    sweep file or a non-rigid sweep pose."""
    sizes = np.asarray(image_size).astype(np.int64)
    parts: list[list[np.ndarray]] = [[] for _ in sample.cameras]
    for k, rec in enumerate((*sample.lidars, *sweeps)):
        if k >= len(sample.lidars):  # the keyframe LiDARs are checked with the sample (validate_sample)
            _check_sweep(rec)
        T = np.stack([sample.T_cam_from_lidar(i, rec) for i in range(len(sample.cameras))])
        uvd_all, counts = project_to_cameras(load_lidar_points(rec.path), T, K, sizes, min_depth)
        for c in range(len(counts)):
            parts[c].append(uvd_all[c, : counts[c]])
    return tuple(np.concatenate(p) if len(p) > 1 else p[0].copy() for p in parts)


def _check_sweep(sweep: LidarRecord) -> None:
    for T, what in ((sweep.T_ego_from_lidar, "calibration"), (sweep.T_global_from_ego, "ego pose")):
        R = T[:3, :3]
        if not np.isfinite(T).all() or not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise SampleError(f"{sweep.channel} sweep {sweep.token!r}: {what} is not a finite rigid transform")


def temporal_indices(scene_index: np.ndarray, index_in_scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Store indices of the previous `N_PREV` keyframes, nearest first, and their validity.

    Samples are in scene order then time order, so the j-th previous frame of sample i is i - j
    when it is in the same scene; otherwise pad with the scene's first frame, invalid (docs/design.md#the-store-layout).
    Returns `(N, N_PREV) int32` and `(N, N_PREV) bool`.
    """
    n = len(scene_index)
    i = np.arange(n)[:, None]
    j = np.arange(1, N_PREV + 1)[None, :]
    valid = index_in_scene[:, None] - j >= 0
    first = (i - index_in_scene[:, None]).astype(np.int64)
    prev = np.where(valid, i - j, first)
    return prev.astype(np.int32), valid
