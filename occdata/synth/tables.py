"""nuScenes tables of the synthetic world: deterministic tokens, static tables, atomic writers."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occdata.fileio import write_atomic
from occdata.nuscenes.lidarseg import LIDARSEG_NAMES

if TYPE_CHECKING:
    from occdata.synth.rig import SynthRig

__all__ = [
    "ATTRIBUTES",
    "TABLE_NAMES",
    "attribute_rows",
    "category_rows",
    "make_token",
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


# A short description of our own for each of the 32 nuScenes-lidarseg categories, in `index` order.
_LIDARSEG_DESCRIPTIONS: tuple[str, ...] = (
    "Points of no surface: reflections, dust, sensor artefacts.",  # noise
    "Any animal.",  # animal
    "An adult person walking or standing.",  # human.pedestrian.adult
    "A child.",  # human.pedestrian.child
    "A person at work on a construction site.",  # human.pedestrian.construction_worker
    "A person on a scooter, skateboard or similar small vehicle.",  # human.pedestrian.personal_mobility
    "A police officer.",  # human.pedestrian.police_officer
    "A stroller or pram.",  # human.pedestrian.stroller
    "A wheelchair.",  # human.pedestrian.wheelchair
    "A temporary barrier on or beside the road.",  # movable_object.barrier
    "Loose debris on the road.",  # movable_object.debris
    "A cart, bin or other object pushed or pulled by hand.",  # movable_object.pushable_pullable
    "A traffic cone.",  # movable_object.trafficcone
    "A rack for parking bicycles.",  # static_object.bicycle_rack
    "A bicycle, with or without rider.",  # vehicle.bicycle
    "An articulated bus.",  # vehicle.bus.bendy
    "A bus with one rigid body.",  # vehicle.bus.rigid
    "A passenger car, van or pick-up.",  # vehicle.car
    "A vehicle for construction work.",  # vehicle.construction
    "An ambulance.",  # vehicle.emergency.ambulance
    "A police vehicle.",  # vehicle.emergency.police
    "A motorcycle or moped, with or without rider.",  # vehicle.motorcycle
    "A trailer towed by another vehicle.",  # vehicle.trailer
    "A vehicle for carrying goods.",  # vehicle.truck
    "Road surface that cars may drive on.",  # flat.driveable_surface
    "Other flat ground: gravel, parking areas, traffic islands.",  # flat.other
    "Pavement for pedestrians.",  # flat.sidewalk
    "Grass, soil and other natural ground.",  # flat.terrain
    "Buildings, walls, poles and other built structures.",  # static.manmade
    "Other static matter.",  # static.other
    "Trees, bushes and other plants above the ground.",  # static.vegetation
    "The recording vehicle itself.",  # vehicle.ego
)

# nuScenes attribute names with a short description of our own.
ATTRIBUTES: tuple[tuple[str, str], ...] = (
    ("vehicle.moving", "The vehicle is moving."),
    ("vehicle.stopped", "The vehicle has stopped briefly, e.g. in traffic, with a driver in it."),
    ("vehicle.parked", "The vehicle is parked."),
    ("cycle.with_rider", "A bicycle or motorcycle with a rider on it."),
    ("cycle.without_rider", "A bicycle or motorcycle without a rider."),
    ("pedestrian.sitting_lying_down", "The person is sitting or lying down."),
    ("pedestrian.standing", "The person is standing."),
    ("pedestrian.moving", "The person is moving."),
)


def category_rows(seed: int) -> list[dict[str, Any]]:
    """The 32 nuScenes-lidarseg categories with their `index` (the label value in lidarseg files)."""
    return [{"token": make_token(seed, "category", name), "name": name, "description": desc, "index": i}
            for i, (name, desc) in enumerate(zip(LIDARSEG_NAMES, _LIDARSEG_DESCRIPTIONS, strict=True))]


def attribute_rows(seed: int) -> list[dict[str, Any]]:
    return [{"token": make_token(seed, "attribute", name), "name": name, "description": desc}
            for name, desc in ATTRIBUTES]


def static_tables(seed: int, rig: SynthRig | None = None) -> dict[str, list[dict[str, Any]]]:
    """Tables that do not depend on the drive: sensor (the rig's; default nuScenes'), category (the 32
    lidarseg categories), attribute, visibility; instance and sample_annotation empty (filled per scene)."""
    if rig is None:
        from occdata.synth.rig import NUSCENES as rig
    sensors = [
        {"token": make_token(seed, "sensor", c.channel), "channel": c.channel, "modality": "camera"}
        for c in rig.cameras
    ] + [{"token": make_token(seed, "sensor", x.channel), "channel": x.channel, "modality": "lidar"}
         for x in rig.lidars]
    levels = [("v0-40", "0 and 40%"), ("v40-60", "40 and 60%"), ("v60-80", "60 and 80%"), ("v80-100", "80 and 100%")]
    return {
        "sensor": sensors,
        "category": category_rows(seed),
        "attribute": attribute_rows(seed),
        "visibility": [
            {"token": str(i + 1), "level": lv, "description": f"visibility of whole object is between {d}"}
            for i, (lv, d) in enumerate(levels)
        ],
        "instance": [],
        "sample_annotation": [],
    }


def write_tables(table_dir: Path, tables: dict[str, list[dict[str, Any]]],
                 names: tuple[str, ...] = TABLE_NAMES) -> None:
    """Write the `names` tables (default nuScenes' 13), and any extra ones (lidarseg), as
    `<table_dir>/<name>.json` (atomic, deterministic formatting; NaN as JSON's `NaN`, as Lyft writes it)."""
    missing = set(names) - set(tables)
    if missing:
        raise ValueError(f"missing tables: {sorted(missing)}")
    for name in (*names, *sorted(set(tables) - set(names))):
        write_atomic(table_dir / f"{name}.json", json.dumps(tables[name], indent=0).encode())
