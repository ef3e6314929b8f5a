"""The store schema (version 2, or 3 with flow): array names, shapes, dtypes, chunking. See docs/store.md.

Every per-sample array has the sample axis first. Small arrays are chunked by blocks of samples;
large label arrays have one chunk per sample inside one shard per block (few files, cheap random
access). Ragged data (JPEG bytes, LiDAR depth points) lives in flat arrays with (start, length)
offsets per (sample, camera); each block of samples owns a chunk-aligned region of them, planned
before any sample is converted (`plan/regions`, version 2), so a task writes its payload in place.
Version 3 is version 2 plus one optional label array, `labels/flow` (OpenOcc v2's per-voxel velocity),
and its checksum column (the last one); a store without flow is version 2, byte for byte as before.
The label arrays take the shape of the store's label grid (`per_sample(flow, shape)`, `grid_shape(attrs)`;
Occ3D's 200 x 200 x 16 by default and for every store whose `grid` attribute names none).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from occdata.constants import CAMERA_ORDER, GRID, LIDAR_CHANNEL
from occdata.errors import OccDataError

__all__ = [
    "FLAT_ARRAYS",
    "FLAT_OF_OFFSETS",
    "MIN_TOKEN_BYTES",
    "N_CAM",
    "camera_count",
    "store_rig",
    "TOKEN_ARRAYS",
    "checksummed_names",
    "token_bytes",
    "token_str",
    "token_width",
    "PER_SAMPLE",
    "READABLE_SCHEMA_VERSIONS",
    "REGIONS",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "STATE_DONE",
    "STATE_ERROR",
    "STATE_PENDING",
    "ArraySpec",
    "FLOW",
    "FLOW_SCHEMA_VERSION",
    "N_PREV",
    "has_flow",
    "grid_shape",
    "label_arrays",
    "per_sample",
    "schema_version",
]

SCHEMA_NAME = "occdata.store"
SCHEMA_VERSION = 2  # 2: every block's ragged payload in its own planned region (gaps between blocks)
# 3: version 2 + `labels/flow` and its checksum column. A version-2 reader refuses it (it would not know
# the extra column), naming the version, instead of calling the checksum table damaged.
FLOW_SCHEMA_VERSION = 3
READABLE_SCHEMA_VERSIONS = (1, 2, 3)  # version 1 (blocks packed back to back) reads the same, through the offsets
N_PREV = 16  # temporal history length (docs/design.md#the-store-layout)
N_CAM = 6

STATE_PENDING, STATE_DONE, STATE_ERROR = 0, 1, 2


@dataclass(frozen=True)
class ArraySpec:
    """One per-sample array: `shape` excludes the leading sample axis."""

    name: str
    shape: tuple[int, ...]
    dtype: str
    fill: int | float = 0
    sharded: bool = False  # one chunk per sample, one shard per block
    checksummed: bool = True


def label_arrays(shape: tuple[int, int, int] = GRID.shape) -> tuple[ArraySpec, ...]:
    """The per-sample arrays shaped by the store's label grid `shape` `(X, Y, Z)` (Occ3D's by default)."""
    return (
        ArraySpec("labels/semantics", shape, "uint8", fill=255, sharded=True),
        ArraySpec("labels/mask_lidar", shape, "uint8", sharded=True),
        ArraySpec("labels/mask_camera", shape, "uint8", sharded=True),
        ArraySpec("labels/bev", shape[:2], "uint32", sharded=True),
        ArraySpec("visibility/present", (), "bool"),
        ArraySpec("visibility/camera", shape, "uint8", sharded=True),
        ArraySpec("visibility/lidar", shape, "uint8", sharded=True),
    )


PER_SAMPLE: tuple[ArraySpec, ...] = (
    # Token arrays: the last axis is widened to the longest token of the store (`token_width`).
    ArraySpec("sample/token", (32,), "uint8"),
    ArraySpec("sample/scene_index", (), "int32"),
    ArraySpec("sample/split", (), "uint8"),  # index into attrs["splits"]
    ArraySpec("sample/index_in_scene", (), "int32"),
    ArraySpec("sample/timestamp", (), "int64"),
    ArraySpec("sample/lidar_token", (32,), "uint8"),
    # Camera arrays: the second axis is widened to the store's cameras (`camera_count`).
    ArraySpec("cam/token", (N_CAM, 32), "uint8"),
    ArraySpec("cam/timestamp", (N_CAM,), "int64"),
    ArraySpec("cam/image_size", (N_CAM, 2), "int32"),
    ArraySpec("calib/K", (N_CAM, 3, 3), "float64"),
    ArraySpec("calib/T_ego_from_cam", (N_CAM, 4, 4), "float64"),
    ArraySpec("calib/T_keyego_from_cam", (N_CAM, 4, 4), "float64"),
    ArraySpec("calib/T_ego_from_lidar", (4, 4), "float64"),
    ArraySpec("pose/T_global_from_keyego", (4, 4), "float64"),
    ArraySpec("pose/T_global_from_ego_cam", (N_CAM, 4, 4), "float64"),
    ArraySpec("temporal/prev_index", (N_PREV,), "int32"),
    ArraySpec("temporal/prev_valid", (N_PREV,), "bool"),
    ArraySpec("images/offsets", (N_CAM, 2), "int64"),
    ArraySpec("depth/offsets", (N_CAM, 2), "int64"),
    ArraySpec("labels/present", (), "bool"),
    *label_arrays(),
    ArraySpec("status/state", (), "uint8", checksummed=False),
    ArraySpec("status/checksum", (), "uint32", checksummed=False),  # shape set from the checksummed count
)

# (vx, vy) m/s per voxel in the grid's (key ego) axes, 0 where static, free or unlabelled. float32: the
# label files' own dtype, so the stored value is the file's value (float16 would round 30 m/s by up to
# 0.008 m/s per component and save ~1/4 of a few kB after zstd: the zeros dominate; docs/store.md).
FLOW = ArraySpec("labels/flow", (*GRID.shape, 2), "float32", sharded=True)


def per_sample(flow: bool = False, shape: tuple[int, int, int] = GRID.shape,
               n_cams: int = N_CAM) -> tuple[ArraySpec, ...]:
    """The per-sample arrays of a store with (or without) `labels/flow`, on a label grid of `shape`,
    with `n_cams` cameras."""
    specs = PER_SAMPLE if n_cams == N_CAM else tuple(_with_cameras(s, n_cams) for s in PER_SAMPLE)
    if tuple(shape) == GRID.shape:
        return specs + ((FLOW,) if flow else ())
    if flow:
        raise OccDataError(f"labels/flow exists on Occ3D's grid only, not on {tuple(shape)}")
    labels = {s.name: s for s in label_arrays(tuple(shape))}  # type: ignore[arg-type]
    return tuple(labels.get(s.name, s) for s in specs)


def _with_cameras(spec: ArraySpec, n_cams: int) -> ArraySpec:
    if spec.name.split("/")[0] in ("cam", "images", "depth") or spec.name in _CAMERA_CALIB:
        return dataclasses.replace(spec, shape=(n_cams, *spec.shape[1:]))
    return spec


_CAMERA_CALIB = ("calib/K", "calib/T_ego_from_cam", "calib/T_keyego_from_cam", "pose/T_global_from_ego_cam")


def store_rig(attrs: Any) -> dict[str, Any]:
    """The rig a store (its root attributes) holds, as `Rig.as_attr`: its `rig` attribute, or for a
    store without one (nuScenes' rig, and every store built before rigs were read) its `camera_order`
    and LIDAR_TOP."""
    rig = attrs.get("rig") if hasattr(attrs, "get") else None
    if isinstance(rig, dict):
        return dict(rig)
    order = attrs.get("camera_order") if hasattr(attrs, "get") else None
    cams = list(order) if isinstance(order, list) and order else list(CAMERA_ORDER)
    return {"cameras": cams, "lidars": [LIDAR_CHANNEL], "reference_lidar": LIDAR_CHANNEL}


def camera_count(attrs: Any) -> int:
    """The number of cameras a store (its root attributes) holds: its `camera_order`; 6 when absent."""
    order = attrs.get("camera_order") if hasattr(attrs, "get") else None
    return len(order) if isinstance(order, list) and order else N_CAM


def grid_shape(attrs: Any) -> tuple[int, int, int]:
    """The label grid shape `(X, Y, Z)` a store (its root attributes) records; Occ3D's when absent."""
    grid = attrs.get("grid") if hasattr(attrs, "get") else None
    shape = grid.get("shape") if isinstance(grid, dict) else None
    if not (isinstance(shape, list) and len(shape) == 3 and all(isinstance(v, int) and v > 0 for v in shape)):
        return GRID.shape
    return (shape[0], shape[1], shape[2])


def schema_version(flow: bool = False) -> int:
    """The version a new store is written with: 3 with flow, else 2 (unchanged)."""
    return FLOW_SCHEMA_VERSION if flow else SCHEMA_VERSION


def has_flow(attrs: Any) -> bool:
    """Whether a store (its root attributes) holds `labels/flow`: schema version 3."""
    return attrs.get("schema_version") == FLOW_SCHEMA_VERSION


# Flat ragged arrays: name -> (row shape, dtype, chunk rows).
FLAT_ARRAYS: dict[str, tuple[tuple[int, ...], str, int]] = {
    "images/jpeg": ((), "uint8", 1 << 20),
    "depth/uvd": ((3,), "float32", 1 << 16),
}

# `(n_blocks, len(FLAT_ARRAYS), 2) int64`: each block's [start, end) rows in each flat array (FLAT_ARRAYS
# order). Written by the build's client only (at creation; again when a block outgrows its region).
REGIONS = "plan/regions"

# Which offsets array indexes which flat array.
FLAT_OF_OFFSETS = {"images/offsets": "images/jpeg", "depth/offsets": "depth/uvd"}


def checksummed_names(flow: bool = False) -> tuple[str, ...]:
    """Arrays covered by the per-sample checksum, in checksum-column order (flat ones next, then
    `labels/flow` last when the store has it: the other columns keep their places)."""
    return tuple(s.name for s in PER_SAMPLE if s.checksummed) + tuple(FLAT_ARRAYS) + ((FLOW.name,) if flow else ())


TOKEN_ARRAYS = ("sample/token", "sample/lidar_token", "cam/token")
MIN_TOKEN_BYTES = 32  # nuScenes tokens: 32 hex characters


def token_width(tokens: Iterable[str]) -> int:
    """Bytes per token in a store holding `tokens`: the longest UTF-8 encoding, at least 32."""
    return max([MIN_TOKEN_BYTES, *(len(t.encode("utf-8")) for t in tokens)])


def token_bytes(token: str, width: int = MIN_TOKEN_BYTES) -> np.ndarray:
    """A token as `(width,) uint8` UTF-8 bytes, zero padded (lossless: tokens hold no NUL).

    Raises `OccDataError` if it does not fit, rather than cutting it (cut tokens collide).
    """
    raw = token.encode("utf-8")
    if len(raw) > width or b"\0" in raw:
        raise OccDataError(f"token {token!r} does not fit the store's {width}-byte token arrays")
    out = np.zeros(width, dtype=np.uint8)
    out[: len(raw)] = np.frombuffer(raw, dtype=np.uint8)
    return out


def token_str(arr: np.ndarray) -> str:
    """The token stored in a `(W,) uint8` row (any W)."""
    return bytes(np.asarray(arr, dtype=np.uint8)).rstrip(b"\0").decode("utf-8", "replace")
