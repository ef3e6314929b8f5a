"""nuScenes-lidarseg: per-point labels of keyframe LIDAR_TOP sweeps, and their Occ3D classes
(docs/design.md#labels-from-lidar).

Files: `<version>/lidarseg.json` rows (token, sample_data_token, filename relative to the root);
each `lidarseg/<version>/<sd_token>_lidarseg.bin` is `uint8`, one label per point of that keyframe
LIDAR_TOP file, in file order. `<version>/category.json` rows carry `index`, the label value.

Occ3D classes: the lidarseg challenge's 16 classes are Occ3D's 1..16 in the same order
(`occdata.constants.CLASS_NAMES`). Of the challenge's ignore classes, `noise` and `vehicle.ego`
points are dropped (`DROP`): noise is no surface and the ego car is not in Occ3D's labels; the rest
(animal, personal mobility, stroller, wheelchair, debris, pushable/pullable, bicycle rack,
ambulance, police vehicle, static.other) are real occupied matter outside the 16 classes, which is
Occ3D's class 0 `others`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from occdata.constants import CLASS_NAMES
from occdata.errors import OccDataError
from occdata.nuscenes.reader import confined_path
from occdata.nuscenes.tables import iter_table_rows

__all__ = [
    "DROP",
    "LIDARSEG_NAMES",
    "OCC3D_FROM_LIDARSEG",
    "load_lidarseg_index",
    "lidarseg_index_names",
    "occ3d_lut",
    "read_lidarseg",
]

DROP = 255  # Occ3D class value meaning "drop this point" (noise, ego vehicle)

# The 32 nuScenes-lidarseg category names in `category.json` `index` order (0..31).
LIDARSEG_NAMES: tuple[str, ...] = (
    "noise",
    "animal",
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer",
    "human.pedestrian.stroller",
    "human.pedestrian.wheelchair",
    "movable_object.barrier",
    "movable_object.debris",
    "movable_object.pushable_pullable",
    "movable_object.trafficcone",
    "static_object.bicycle_rack",
    "vehicle.bicycle",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.car",
    "vehicle.construction",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.motorcycle",
    "vehicle.trailer",
    "vehicle.truck",
    "flat.driveable_surface",
    "flat.other",
    "flat.sidewalk",
    "flat.terrain",
    "static.manmade",
    "static.other",
    "static.vegetation",
    "vehicle.ego",
)

_C = {name: i for i, name in enumerate(CLASS_NAMES)}
_OTHERS = _C["others"]

# lidarseg category name -> Occ3D class 0..16, or DROP.
OCC3D_FROM_LIDARSEG: dict[str, int] = {
    "noise": DROP,
    "animal": _OTHERS,
    "human.pedestrian.adult": _C["pedestrian"],
    "human.pedestrian.child": _C["pedestrian"],
    "human.pedestrian.construction_worker": _C["pedestrian"],
    "human.pedestrian.personal_mobility": _OTHERS,
    "human.pedestrian.police_officer": _C["pedestrian"],
    "human.pedestrian.stroller": _OTHERS,
    "human.pedestrian.wheelchair": _OTHERS,
    "movable_object.barrier": _C["barrier"],
    "movable_object.debris": _OTHERS,
    "movable_object.pushable_pullable": _OTHERS,
    "movable_object.trafficcone": _C["traffic_cone"],
    "static_object.bicycle_rack": _OTHERS,
    "vehicle.bicycle": _C["bicycle"],
    "vehicle.bus.bendy": _C["bus"],
    "vehicle.bus.rigid": _C["bus"],
    "vehicle.car": _C["car"],
    "vehicle.construction": _C["construction_vehicle"],
    "vehicle.emergency.ambulance": _OTHERS,
    "vehicle.emergency.police": _OTHERS,
    "vehicle.motorcycle": _C["motorcycle"],
    "vehicle.trailer": _C["trailer"],
    "vehicle.truck": _C["truck"],
    "flat.driveable_surface": _C["driveable_surface"],
    "flat.other": _C["other_flat"],
    "flat.sidewalk": _C["sidewalk"],
    "flat.terrain": _C["terrain"],
    "static.manmade": _C["manmade"],
    "static.other": _OTHERS,
    "static.vegetation": _C["vegetation"],
    "vehicle.ego": DROP,
}


def load_lidarseg_index(root: Path, version: str) -> dict[str, Path]:
    """sample_data token -> absolute path of its `.bin` label file, from `<root>/<version>/lidarseg.json`.

    Paths are `root / filename` (not resolved, like the reader's record paths) and must stay inside
    `root`. `{}` when lidarseg.json is absent (no lidarseg for this version). A row without a string
    `sample_data_token`, or two rows for one sample_data token, is an `OccDataError` naming the row.
    """
    path = Path(root) / version / "lidarseg.json"
    if not path.is_file():
        return {}
    out: dict[str, Path] = {}
    for row in iter_table_rows(path):
        where = f"lidarseg.json row {row.get('token', '?')!r}"
        sd_token = row.get("sample_data_token")
        if not isinstance(sd_token, str) or not sd_token:
            raise OccDataError(f"{where} has no string sample_data_token ({path})")
        if sd_token in out:
            raise OccDataError(f"{where}: sample_data {sd_token!r} has two lidarseg rows ({path})")
        out[sd_token] = confined_path(Path(root), row.get("filename"), f"{where} filename")
    return out


def read_lidarseg(path: Path, n_points: int) -> np.ndarray:
    """The labels of one keyframe sweep: `(n_points,) uint8` lidarseg indices, in point-file order.

    Raises `OccDataError` naming the file when it is missing or unreadable, or when its length is
    not `n_points` bytes (the label file must match its point cloud).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise OccDataError(f"missing lidarseg file: {path}") from None
    except OSError as exc:
        raise OccDataError(f"cannot read lidarseg file {path}: {exc.strerror or exc}") from None
    if len(raw) != n_points:
        raise OccDataError(f"lidarseg file {path} holds {len(raw)} labels, its point cloud has {n_points} points")
    return np.frombuffer(raw, dtype=np.uint8).copy()


def lidarseg_index_names(root: Path, version: str) -> dict[int, str]:
    """`category.json` `index` -> category name, for the rows that carry an `index` (0..255).

    Raises `OccDataError` naming the table and token for a non-integer or out-of-range index or
    two categories sharing one index.
    """
    path = Path(root) / version / "category.json"
    out: dict[int, str] = {}
    for row in iter_table_rows(path):
        if "index" not in row:
            continue
        where = f"category.json row {row.get('token', '?')!r}"
        index: Any = row["index"]
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index <= 255:
            raise OccDataError(f"{where}: index {index!r} is not an integer 0..255")
        name = row.get("name")
        if not isinstance(name, str):
            raise OccDataError(f"{where} has no string name")
        if index in out:
            raise OccDataError(f"{where}: index {index} is also category {out[index]!r}")
        out[index] = name
    return out


def occ3d_lut(index_names: dict[int, str]) -> np.ndarray:
    """`(256,) uint8` lookup table: lidarseg index -> Occ3D class 0..16, `DROP` (255) to drop.

    Indices not in `index_names` map to `DROP`; a name not among `LIDARSEG_NAMES` is an
    `OccDataError` (an unknown category has no defined Occ3D class).
    """
    lut = np.full(256, DROP, dtype=np.uint8)
    for index, name in index_names.items():
        if name not in OCC3D_FROM_LIDARSEG:
            raise OccDataError(
                f"category.json: lidarseg category {name!r} (index {index}) is not a nuScenes-lidarseg class"
            )
        lut[index] = OCC3D_FROM_LIDARSEG[name]
    return lut
