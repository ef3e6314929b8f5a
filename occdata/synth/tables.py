"""nuScenes tables of the synthetic world: deterministic tokens, static tables, atomic writers."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from occdata.constants import CAMERA_ORDER, LIDAR_CHANNEL
from occdata.fileio import write_atomic

__all__ = [
    "TABLE_NAMES",
    "make_token",
    "npz_bytes",
    "static_tables",
    "write_atomic",
    "write_tables",
]

TABLE_NAMES = (
    "attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
    "sample_annotation", "sample_data", "scene", "sensor", "visibility",
)


def make_token(seed: int, *parts: object) -> str:
    """A 32-hex-character token, a pure function of the seed and the record's identity."""
    key = ":".join(["occdata-synth", str(seed), *map(str, parts)])
    return hashlib.md5(key.encode()).hexdigest()


def static_tables(seed: int) -> dict[str, list[dict[str, Any]]]:
    """Tables that do not depend on the drive: sensor, category, attribute, visibility (the last
    three minimal but valid; this world carries no box annotations)."""
    sensors = [
        {"token": make_token(seed, "sensor", ch), "channel": ch, "modality": "camera"} for ch in CAMERA_ORDER
    ] + [{"token": make_token(seed, "sensor", LIDAR_CHANNEL), "channel": LIDAR_CHANNEL, "modality": "lidar"}]
    categories = [
        ("human.pedestrian.adult", "Adult subcategory."),
        ("vehicle.car", "Vehicle designed primarily for personal use."),
        ("vehicle.bus.rigid", "Rigid bus."),
        ("vehicle.truck", "Vehicles primarily designed to haul cargo."),
        ("vehicle.bicycle", "Human or electric powered 2-wheeled vehicle."),
        ("vehicle.motorcycle", "Gasoline or electric powered 2-wheeled vehicle."),
        ("movable_object.barrier", "Temporary road barrier."),
        ("movable_object.trafficcone", "Traffic cone."),
    ]
    attributes = [("vehicle.moving", "Vehicle is moving."), ("vehicle.parked", "Vehicle is parked."),
                  ("pedestrian.moving", "The human is moving."), ("pedestrian.standing", "The human is standing.")]
    levels = [("v0-40", "0 and 40%"), ("v40-60", "40 and 60%"), ("v60-80", "60 and 80%"), ("v80-100", "80 and 100%")]
    return {
        "sensor": sensors,
        "category": [{"token": make_token(seed, "category", n), "name": n, "description": d} for n, d in categories],
        "attribute": [{"token": make_token(seed, "attribute", n), "name": n, "description": d} for n, d in attributes],
        "visibility": [
            {"token": str(i + 1), "level": lv, "description": f"visibility of whole object is between {d}"}
            for i, (lv, d) in enumerate(levels)
        ],
        "instance": [],
        "sample_annotation": [],
    }


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed .npz archive with fixed zip timestamps (np.savez stamps the current time)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def write_tables(table_dir: Path, tables: dict[str, list[dict[str, Any]]]) -> None:
    """Write all 13 tables as `<table_dir>/<name>.json` (atomic, deterministic formatting)."""
    missing = set(TABLE_NAMES) - set(tables)
    if missing:
        raise ValueError(f"missing tables: {sorted(missing)}")
    for name in TABLE_NAMES:
        write_atomic(table_dir / f"{name}.json", json.dumps(tables[name], indent=0).encode())
