"""Label grids as values: voxel size, range, frame, class map and file layout (docs/labels.md, "Grids").

Four benchmarks' grids are named presets; `custom_grid` makes any other one. A grid spec says where a
voxel is (`grid`, in `frame`), what its class ids mean (`class_map`: the target id of each of our 18
Occ3D classes) and how its files look (`layout`; the writers and readers are `occdata.formats.gridfiles`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from occdata.constants import CLASS_NAMES, FREE_LABEL, GRID, NUM_CLASSES, OccGrid
from occdata.errors import OccDataError

__all__ = ["GRID_NAMES", "GRID_PRESETS", "GridSpec", "LabelFrame", "LabelLayout", "custom_grid", "grid_preset",
           "grids_from_options"]


class LabelFrame(StrEnum):
    """The frame a grid is laid out in, at the keyframe's LIDAR_TOP timestamp."""

    KEY_EGO = "key_ego"  # the ego vehicle (x forward from the rear axle, y left, z up): Occ3D, OpenOcc v2
    LIDAR = "lidar"  # the LIDAR_TOP sensor itself (z up from the sensor, ~1.8 m above the road)


class LabelLayout(StrEnum):
    """How a grid's labels are stored (occdata.formats.gridfiles)."""

    OCC3D = "occ3d"  # <scene>/<sample token>/labels.npz: semantics, mask_lidar, mask_camera (X, Y, Z) uint8
    OPENOCC_V2 = "openocc-v2"  # <scene>/<sample token>/labels.npz: semantics (own class order), flow, masks
    SURROUNDOCC = "surroundocc"  # samples/<LiDAR file name>.npy: (N, 4) [x, y, z, class] of the occupied voxels
    OPENOCCUPANCY = "openoccupancy"  # scene_<scene token>/occupancy/<LiDAR sample_data token>.npy: [z, y, x, class]


# Target id of each Occ3D class (index = our id: others, barrier, ..., vegetation, free).
_OCC3D_IDS = tuple(range(NUM_CLASSES))
# nuScenes-lidarseg's 16 evaluation classes keep our order 1..16; "others" has no class there (noise, 0).
_LIDARSEG16_IDS = (0, *range(1, FREE_LABEL), 0)
# OpenOcc v2: car, truck, trailer, bus, construction_vehicle, bicycle, motorcycle, pedestrian, traffic_cone,
# barrier, driveable_surface, other_flat, sidewalk, terrain, manmade, vegetation (0..15), free 16. It has no
# "others" class and no ignore id: our "others" voxels are written as free (docs/labels.md).
_OPENOCC_NAMES = ("car", "truck", "trailer", "bus", "construction_vehicle", "bicycle", "motorcycle", "pedestrian",
                  "traffic_cone", "barrier", "driveable_surface", "other_flat", "sidewalk", "terrain", "manmade",
                  "vegetation", "free")
_OPENOCC_IDS = tuple(_OPENOCC_NAMES.index(n if n in _OPENOCC_NAMES else "free") for n in CLASS_NAMES)


@dataclass(frozen=True)
class GridSpec:
    """One label grid. `class_map[k]` is the stored id of Occ3D class k (k = 0..17, 17 = free);
    `class_names[i]` names stored id i; `free_value` is what free space is stored as (a sparse layout
    stores no free voxel at all). `masks`: the layout carries mask_lidar / mask_camera."""

    name: str
    grid: OccGrid
    frame: LabelFrame
    layout: LabelLayout
    class_map: tuple[int, ...]
    class_names: tuple[str, ...]
    free_value: int
    masks: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame", LabelFrame(self.frame))
        object.__setattr__(self, "layout", LabelLayout(self.layout))
        bad = []
        g = self.grid
        if not 0.05 <= g.voxel_size <= 2.0:
            bad.append(f"voxel size {g.voxel_size} m (use 0.05-2 m)")
        for lo, hi in zip(g.lower, g.upper, strict=True):
            n = (hi - lo) / g.voxel_size
            if hi <= lo or abs(n - round(n)) > 1e-6:
                bad.append(f"range [{lo}, {hi}] is not a positive whole number of {g.voxel_size} m voxels")
        if len(self.class_map) != NUM_CLASSES or not all(0 <= c < len(self.class_names) for c in self.class_map):
            bad.append(f"class_map needs {NUM_CLASSES} ids within the {len(self.class_names)} class names")
        if not 0 <= self.free_value < 256:
            bad.append(f"free_value {self.free_value} (0..255)")
        if not bad and math.prod(self.shape) > 64 * 2**20:
            bad.append(f"{self.shape} is {math.prod(self.shape) / 2**20:.0f} M voxels (at most 64 M)")
        if bad:
            raise ValueError(f"bad grid {self.name!r}: " + "; ".join(bad))

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.grid.shape

    def lut(self) -> np.ndarray:
        """`(256,) uint8`: Occ3D class -> stored id (ids above 17, e.g. 255 unknown, map to free)."""
        out = np.full(256, self.free_value, np.uint8)
        out[:NUM_CLASSES] = self.class_map
        return out

    def describe(self) -> dict[str, object]:
        """The manifest's words for this grid."""
        g = self.grid
        return {"name": self.name, "voxel_size": g.voxel_size, "lower": list(g.lower), "upper": list(g.upper),
                "shape": list(self.shape), "frame": str(self.frame), "layout": str(self.layout),
                "classes": {name: i for i, name in enumerate(self.class_names)}, "free_value": self.free_value,
                "masks": self.masks,
                "from_occ3d": {CLASS_NAMES[k]: int(v) for k, v in enumerate(self.class_map)}}

    @classmethod
    def from_description(cls, d: dict[str, object]) -> GridSpec:
        """The grid that `describe()` gave `d` (a manifest's or a store's words); `ValueError` if they are
        incomplete or inconsistent."""
        try:
            classes = dict(d["classes"])  # type: ignore[call-overload]
            names = tuple(sorted(classes, key=classes.__getitem__))
            if [classes[n] for n in names] != list(range(len(names))):
                raise ValueError("class ids are not 0..N-1")
            from_occ3d = dict(d["from_occ3d"])  # type: ignore[call-overload]
            spec = cls(str(d["name"]), OccGrid(tuple(map(float, d["lower"])), tuple(map(float, d["upper"])),  # type: ignore[call-overload, arg-type]
                                               float(d["voxel_size"])),  # type: ignore[arg-type]
                       LabelFrame(d["frame"]), LabelLayout(d["layout"]),
                       tuple(int(from_occ3d[n]) for n in CLASS_NAMES), names, int(d["free_value"]),  # type: ignore[call-overload]
                       bool(d["masks"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a grid description ({type(exc).__name__}: {exc})") from None
        if list(spec.shape) != list(d.get("shape", spec.shape)):  # type: ignore[call-overload]
            raise ValueError(f"grid {spec.name}: shape {d.get('shape')} does not follow from its range")
        return spec


GRID_PRESETS: dict[str, GridSpec] = {g.name: g for g in (
    GridSpec("occ3d", GRID, LabelFrame.KEY_EGO, LabelLayout.OCC3D, _OCC3D_IDS, CLASS_NAMES, FREE_LABEL),
    GridSpec("openocc-v2", GRID, LabelFrame.KEY_EGO,
             LabelLayout.OPENOCC_V2, _OPENOCC_IDS, _OPENOCC_NAMES, _OPENOCC_NAMES.index("free")),
    GridSpec("surroundocc", OccGrid((-50.0, -50.0, -5.0), (50.0, 50.0, 3.0), 0.5), LabelFrame.LIDAR,
             LabelLayout.SURROUNDOCC, _LIDARSEG16_IDS, ("noise", *CLASS_NAMES[1:17]), 0, masks=False),
    GridSpec("openoccupancy", OccGrid((-51.2, -51.2, -5.0), (51.2, 51.2, 3.0), 0.2), LabelFrame.LIDAR,
             LabelLayout.OPENOCCUPANCY, _LIDARSEG16_IDS, ("noise", *CLASS_NAMES[1:17]), 0, masks=False),
)}


def grid_preset(name: str) -> GridSpec:
    if name not in GRID_PRESETS:
        raise ValueError(f"unknown grid {name!r}; choose from {', '.join(GRID_PRESETS)} or give a voxel size")
    return GRID_PRESETS[name]


def custom_grid(voxel_size: float, lower: tuple[float, float, float], upper: tuple[float, float, float],
                base: str = "occ3d") -> GridSpec:
    """`base`'s frame, classes and layout on another voxel size and range (named like "occ3d-0.2m")."""
    b = grid_preset(base)
    return GridSpec(f"{base}-{voxel_size:g}m", OccGrid(tuple(lower), tuple(upper), float(voxel_size)),  # type: ignore[arg-type]
                    b.frame, b.layout, b.class_map, b.class_names, b.free_value, b.masks)


GRID_NAMES = tuple(GRID_PRESETS)


def grids_from_options(names: tuple[str, ...] = (), voxel_size: float | None = None,
                       grid_range: tuple[float, ...] | None = None) -> tuple[GridSpec, ...]:
    """The grids of `occdata labels --grid ... [--voxel-size V] [--range ...]`: the named presets, plus a
    custom Occ3D-style grid when a voxel size or a range is given; Occ3D's alone when nothing is."""
    try:
        specs = [grid_preset(n) for n in dict.fromkeys(names)]
        if voxel_size is not None or grid_range is not None:
            occ = GRID_PRESETS["occ3d"].grid
            lo, hi = (occ.lower, occ.upper) if grid_range is None else (tuple(grid_range[:3]), tuple(grid_range[3:]))
            specs.append(custom_grid(occ.voxel_size if voxel_size is None else voxel_size, lo, hi))
    except ValueError as exc:
        raise OccDataError(str(exc)) from None
    return tuple(specs) or (GRID_PRESETS["occ3d"],)
