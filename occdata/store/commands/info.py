"""`occdata info` and `occdata dump`: a store described, and one sample as plain numpy arrays."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from occdata.constants import CAMERA_ORDER
from occdata.errors import OccDataError
from occdata.fileio import atomic_open
from occdata.store.bev import unpack_bev
from occdata.store.layout import FLAT_ARRAYS, STATE_DONE, STATE_ERROR, STATE_PENDING, per_sample, store_rig
from occdata.store.reader import StoreReader

__all__ = ["DUMP_KEYS", "dump_sample", "grid_summary", "store_info"]


def store_info(reader: StoreReader) -> dict[str, Any]:
    state = reader.state
    arrays = {}
    for name in [s.name for s in per_sample(reader.has_flow, reader.grid_shape, reader.n_cams)] + list(FLAT_ARRAYS):
        a = reader.group[name]
        shards = getattr(a, "shards", None)
        arrays[name] = {"shape": list(a.shape), "dtype": str(a.dtype), "chunks": list(a.chunks),
                        "shards": list(shards) if shards else None}
    attrs = dict(reader.attrs)
    scenes = attrs.pop("scenes", [])
    errors = attrs.pop("errors", [])
    return {
        "store": reader.path,
        "samples": reader.n_samples,
        "done": int((state == STATE_DONE).sum()),
        "errors": int((state == STATE_ERROR).sum()),
        "pending": int((state == STATE_PENDING).sum()),
        "labelled": int(reader.group["labels/present"][:].sum()),
        "with_visibility": int(reader.group["visibility/present"][:].sum()),
        "flow": reader.has_flow,
        "grid": grid_summary(reader),
        "rig": store_rig(reader.attrs),
        "scenes": len(scenes),
        "scene_table": scenes,
        "recorded_errors": errors,
        "arrays": arrays,
        "attrs": attrs,
    }


def grid_summary(reader: StoreReader) -> dict[str, Any]:
    """The store's label grid: name, voxel size, range, shape, frame, source layout, masks, and a line."""
    g = reader.grid
    d = {k: v for k, v in g.describe().items() if k not in ("classes", "from_occ3d", "free_value")}
    named = "name" in reader.attrs.get("grid", {})
    masks = ("the grid's own masks" if g.masks else "none in the source: all-ones masks") if named else "Occ3D's"
    lo, hi = g.grid.lower, g.grid.upper
    d["line"] = (f"{g.name}: {g.grid.voxel_size:g} m voxels, {'x'.join(map(str, g.shape))}, "
                 f"x {lo[0]:g}..{hi[0]:g} y {lo[1]:g}..{hi[1]:g} z {lo[2]:g}..{hi[2]:g} m in the "
                 f"{'key ego' if g.frame == 'key_ego' else 'LIDAR_TOP'} frame; labels in our 18 Occ3D ids; masks: "
                 f"{masks}")
    return d


DUMP_KEYS = {
    "images": "(6, H, W, 3) uint8 RGB, decoded stored JPEGs, camera order in attrs",
    "camera_order": "(6,) str",
    "K": "(6, 3, 3) float64 intrinsics of the original image",
    "T_ego_from_cam": "(6, 4, 4) float64",
    "T_keyego_from_cam": "(6, 4, 4) float64",
    "T_ego_from_lidar": "(4, 4) float64",
    "T_global_from_keyego": "(4, 4) float64",
    "T_global_from_ego_cam": "(6, 4, 4) float64",
    "depth_uvd_<c>": "(M_c, 3) float32 per camera c = 0..5: u, v (original pixels), depth (m)",
    "semantics / mask_lidar / mask_camera": "(X, Y, Z) uint8, the store's grid ((200, 200, 16) on Occ3D's; "
                                            "absent without labels)",
    "flow": "(200, 200, 16, 2) float32 (vx, vy) m/s in key ego (stores with flow, labelled samples only)",
    "bev": "(18, X, Y) uint8 multi-hot (absent without labels)",
    "visibility_camera / visibility_lidar": "(X, Y, Z) uint8 (absent until `occdata visibility`)",
    "prev_index / prev_valid": "(16,) int32 / bool temporal indices, nearest first",
    "token / timestamp": "str / int64",
}


def dump_sample(reader: StoreReader, index: int, out: Path) -> list[str]:
    """Write one sample as a plain `.npz` (no pickles); returns the keys written.

    Failed or pending samples raise `OccDataError`; a failed write (e.g. a full disk) leaves no
    partial file behind.
    """
    reader.require_done(index)
    a = reader.sample_arrays(index)
    images = reader.images(index)
    data: dict[str, np.ndarray] = {
        "token": np.array(reader.token(index)),
        "timestamp": a["sample/timestamp"],
        "camera_order": np.array(reader.attrs.get("camera_order", list(CAMERA_ORDER))),
        "K": a["calib/K"],
        "T_ego_from_cam": a["calib/T_ego_from_cam"],
        "T_keyego_from_cam": a["calib/T_keyego_from_cam"],
        "T_ego_from_lidar": a["calib/T_ego_from_lidar"],
        "T_global_from_keyego": a["pose/T_global_from_keyego"],
        "T_global_from_ego_cam": a["pose/T_global_from_ego_cam"],
        "prev_index": a["temporal/prev_index"],
        "prev_valid": a["temporal/prev_valid"],
    }
    if len({im.shape for im in images}) == 1:
        data["images"] = np.stack(images)
    else:
        data.update({f"image_{c}": im for c, im in enumerate(images)})
    for c, pts in enumerate(reader.depth_points(index)):
        data[f"depth_uvd_{c}"] = pts
    if a["labels/present"]:
        for k in ("semantics", "mask_lidar", "mask_camera"):
            data[k] = a[f"labels/{k}"]
        data["bev"] = unpack_bev(a["labels/bev"])
        if "labels/flow" in a:
            data["flow"] = a["labels/flow"]
    if a["visibility/present"]:
        data["visibility_camera"] = a["visibility/camera"]
        data["visibility_lidar"] = a["visibility/lidar"]
    try:
        with atomic_open(out) as f:
            np.savez_compressed(f, **data)
    except OSError as exc:
        raise OccDataError(f"cannot write {out}: {exc.strerror or exc}") from None
    return sorted(data)
