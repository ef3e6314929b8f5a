"""A store's label grid: what `attrs["grid"]` records, and the `GridSpec` read back from it (docs/store.md,
"The label grid").

A store on Occ3D's grid keeps the attribute it always had (lower, upper, voxel size, shape, a frame in
words, axis order: no name), so its bytes are unchanged; `store_grid` reads that as the occ3d preset.
A store on any other grid records the grid's full description (`GridSpec.describe()`) plus what the
store made of it: labels are always stored in our 18 Occ3D ids, and a grid without masks gets all-ones
masks.
"""

from __future__ import annotations

from typing import Any

from occdata.constants import GRID
from occdata.errors import OccDataError
from occdata.formats.gridspec import GRID_PRESETS, GridSpec, LabelFrame

__all__ = ["OCC3D_GRID_ATTR", "grid_attr", "is_default_grid", "store_grid"]

# Occ3D's grid as every store before grids recorded it (kept byte for byte).
OCC3D_GRID_ATTR: dict[str, Any] = {
    "lower": list(GRID.lower), "upper": list(GRID.upper), "voxel_size": GRID.voxel_size, "shape": list(GRID.shape),
    "frame": "key ego (LIDAR_TOP keyframe ego pose)", "axis_order": "x, y, z",
}
_NO_MASK = ("none: the grid's labels have no masks; labels/mask_lidar and labels/mask_camera are all ones "
            "(every voxel counts)")


def is_default_grid(spec: GridSpec | None) -> bool:
    """Occ3D's geometry, stored as before: the occ3d preset itself, or OpenOcc v2's (its files are read
    by the flow path, on the same 200 x 200 x 16 key-ego grid)."""
    return spec is None or spec == GRID_PRESETS["occ3d"] or spec == GRID_PRESETS["openocc-v2"]


def grid_attr(spec: GridSpec | None) -> dict[str, Any]:
    """`attrs["grid"]` of a store whose labels come from files of `spec` (None: Occ3D's grid)."""
    if is_default_grid(spec):
        return dict(OCC3D_GRID_ATTR)
    assert spec is not None
    frame = ("key ego (LIDAR_TOP keyframe ego pose)" if spec.frame is LabelFrame.KEY_EGO
             else "LIDAR_TOP sensor at the keyframe (calib/T_ego_from_lidar takes it to key ego)")
    return spec.describe() | {
        "axis_order": "x, y, z", "frame_words": frame,
        "stored_ids": "ours: the store's class_names (18 Occ3D classes, free_label free); 'classes' and "
                      "'from_occ3d' describe the source files' ids",
        "mask": "the grid's own masks" if spec.masks else _NO_MASK,
    }


def store_grid(attrs: Any) -> GridSpec:
    """The label grid a store (its root attributes) records: its description, or Occ3D's preset for
    a store that records the Occ3D geometry without a name (every store before grids)."""
    grid = attrs.get("grid")
    if not isinstance(grid, dict) or "name" not in grid:
        if grid is not None and isinstance(grid, dict) and grid.get("shape", list(GRID.shape)) != list(GRID.shape):
            raise OccDataError(f"store grid attribute {grid!r}: not Occ3D's grid and no grid description")
        return GRID_PRESETS["occ3d"]
    try:
        return GridSpec.from_description(grid)
    except ValueError as exc:
        raise OccDataError(f"store grid attribute: {exc}") from None
