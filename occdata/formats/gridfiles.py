"""Label files of every grid layout: where they go (`LAYOUT_FILES` says it in words, for manifests),
writing them, and reading them as each benchmark's own loader does (docs/labels.md, "Grids"; the
formats were checked against each benchmark's code, docs/label_formats.md).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occdata.constants import FREE_LABEL
from occdata.errors import OccDataError
from occdata.fileio import write_atomic
from occdata.formats.gridspec import GridSpec, LabelLayout
from occdata.formats.occ3d import label_path, write_label

__all__ = ["IGNORE", "LAYOUT_FILES", "LabelSite", "grid_label_path", "read_grid_label", "to_occ3d_ids",
           "write_grid_label"]

IGNORE = 255  # what the sparse layouts' loaders turn noise (class 0) into

# Each layout's files in words (the manifest's "files"; the writer below is the definition).
LAYOUT_FILES: dict[LabelLayout, str] = {
    LabelLayout.OCC3D: "<scene>/<sample_token>/labels.npz: semantics, mask_lidar, mask_camera, uint8 (X, Y, Z) in "
                       "the key ego frame; ids as 'classes' (17 = free); masks 0/1",
    LabelLayout.OPENOCC_V2: "<scene>/<sample_token>/labels.npz: semantics uint8 (X, Y, Z) in OpenOcc v2's ids (16 = "
                            "free; our 'others' written as free), flow float32 (X, Y, Z, 2) (vx, vy) m/s in the key "
                            "ego frame (zero where not computed), mask_lidar, mask_camera (extra keys its loader "
                            "ignores)",
    LabelLayout.SURROUNDOCC: "samples/<LIDAR_TOP file name>.npy: int64 (N, 4) [x, y, z, class] of the occupied voxels "
                             "in the keyframe's LIDAR_TOP frame; class 0 = noise (our 'others'), absent voxels "
                             "empty; no masks",
    LabelLayout.OPENOCCUPANCY: "scene_<scene token>/occupancy/<LIDAR_TOP sample_data token>.npy: int64 (N, 4) [z, y, "
                               "x, class] of the occupied voxels in the LIDAR_TOP frame; class 0 = noise; no masks",
}


@dataclass(frozen=True)
class LabelSite:
    """What names a keyframe's label file in the four layouts."""

    scene_name: str
    scene_token: str
    sample_token: str
    lidar_token: str  # the keyframe's LIDAR_TOP sample_data token
    lidar_file: str  # its file name, e.g. n008-...__LIDAR_TOP__1537297541450317.pcd.bin


def grid_label_path(spec: GridSpec, root: str | Path, site: LabelSite) -> Path:
    root = Path(root)
    if spec.layout is LabelLayout.SURROUNDOCC:
        return root / "samples" / f"{site.lidar_file}.npy"
    if spec.layout is LabelLayout.OPENOCCUPANCY:
        return root / f"scene_{site.scene_token}" / "occupancy" / f"{site.lidar_token}.npy"
    return label_path(root, site.scene_name, site.sample_token)


def write_grid_label(spec: GridSpec, root: str | Path, site: LabelSite, labels: dict[str, np.ndarray]) -> Path:
    """Write one keyframe's labels on `spec` atomically (the same bytes for the same labels).

    labels: `semantics` `(X, Y, Z) uint8` in Occ3D classes (17 = free), and where the layout has them
    `mask_lidar`, `mask_camera` `(X, Y, Z) uint8` and `flow` `(X, Y, Z, 2) float32`."""
    sem = labels["semantics"]
    if sem.shape != spec.shape:
        raise OccDataError(f"labels of shape {sem.shape} for grid {spec.name} {spec.shape}")
    path = grid_label_path(spec, root, site)
    stored = spec.lut()[sem]
    if spec.layout in (LabelLayout.SURROUNDOCC, LabelLayout.OPENOCCUPANCY):
        xyz = np.argwhere(sem != FREE_LABEL)  # (N, 3) x, y, z in C order: sorted, so the bytes are fixed
        cols = xyz if spec.layout is LabelLayout.SURROUNDOCC else xyz[:, ::-1]
        rows = np.concatenate([cols, stored[tuple(xyz.T)][:, None]], axis=1).astype(np.int64)
        buf = io.BytesIO()
        np.lib.format.write_array(buf, rows, allow_pickle=False)
        write_atomic(path, buf.getvalue())
        return path
    arrays = {"semantics": stored}
    arrays |= {k: labels[k] for k in ("mask_lidar", "mask_camera") if k in labels}
    if spec.layout is LabelLayout.OPENOCC_V2:
        flow = labels.get("flow")
        arrays["flow"] = np.zeros((*spec.shape, 2), np.float32) if flow is None else flow.astype(np.float32)
    write_label(path, arrays)
    return path


def read_grid_label(spec: GridSpec, path: str | Path) -> dict[str, np.ndarray]:
    """A label file of `spec` as its benchmark's loader reads it: `semantics` `(X, Y, Z) uint8` dense in
    the grid's own ids (sparse layouts: 0 = empty, noise -> IGNORE), plus `flow` (openocc-v2) and the
    masks where the file has them. One `OccDataError` per bad file."""
    path = Path(path)
    try:
        loaded = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise OccDataError(f"bad {spec.name} label {path}: {type(exc).__name__}: {exc}") from None
    if spec.layout in (LabelLayout.SURROUNDOCC, LabelLayout.OPENOCCUPANCY):
        return {"semantics": _dense(spec, path, np.asarray(loaded))}
    with loaded as npz:
        out = {k: np.asarray(npz[k]) for k in npz.files}
    if out.get("semantics", np.zeros(0)).shape != spec.shape:
        raise OccDataError(f"bad {spec.name} label {path}: semantics missing or not of shape {spec.shape}")
    return out


def _dense(spec: GridSpec, path: Path, rows: np.ndarray) -> np.ndarray:
    """Sparse (N, 4) rows -> dense `(X, Y, Z) uint8`: 0 empty, noise (class 0) -> IGNORE."""
    if rows.ndim != 2 or rows.shape[1] != 4 or rows.dtype.kind not in "iu":
        raise OccDataError(f"bad {spec.name} label {path}: expected (N, 4) integer rows, got {rows.shape} {rows.dtype}")
    xyz = rows[:, :3] if spec.layout is LabelLayout.SURROUNDOCC else rows[:, 2::-1]
    if len(rows) and ((xyz < 0).any() or (xyz >= np.array(spec.shape)).any()):
        raise OccDataError(f"bad {spec.name} label {path}: voxel indices outside {spec.shape}")
    cls = rows[:, 3].copy()
    cls[cls == 0] = IGNORE
    dense = np.zeros(spec.shape, np.uint8)
    dense[tuple(xyz.T)] = cls
    return dense


def to_occ3d_ids(spec: GridSpec, stored: np.ndarray) -> np.ndarray:
    """`(X, Y, Z) uint8` in the grid's own ids (as `read_grid_label` returns them) -> our 18 classes:
    free 17; the sparse layouts' empty 0 -> free and noise (IGNORE) -> others (0)."""
    inv = np.full(256, FREE_LABEL, np.uint8)
    for ours in range(FREE_LABEL - 1, -1, -1):  # many-to-one: the lowest of our ids wins
        if spec.class_map[ours] != spec.free_value:
            inv[spec.class_map[ours]] = ours
    if spec.layout in (LabelLayout.SURROUNDOCC, LabelLayout.OPENOCCUPANCY):
        inv[0], inv[IGNORE] = FREE_LABEL, 0
    return inv[stored]
