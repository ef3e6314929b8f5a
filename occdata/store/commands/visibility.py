"""`occdata visibility`: Occ3D-style camera and LiDAR masks for a store
(docs/design.md#visibility-masks, docs/visibility.md).

Occupancy comes from the stored semantics, so labelled samples are needed. The LiDAR rays are the
keyframe points stored as depth targets (points inside some camera image), un-projected exactly
into the key-ego frame; or, with `lidar_sweeps` (Occ3D aggregates sweeps), every point of the
source tree's keyframe sweep and of up to N previous sweeps, each ray from its own sensor position,
moved into key ego through global. A store of several LiDARs always takes its rays from the source
tree (the stored depth points do not say which LiDAR saw them): every LiDAR's keyframe sweep, each
from its own origin. `occdata.visibility.lidar_mask` adds every object voxel, as
Occ3D's mask does. The camera mask lies within the sample's LiDAR mask: the label's own `mask_lidar` when it
ships one, else the computed one (a label-only store).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

from occdata.constants import FREE_LABEL, GRID, NUM_CLASSES, OccGrid
from occdata.errors import OccDataError
from occdata.formats.gridspec import LabelFrame
from occdata.geometry import invert_rigid, transform_points
from occdata.nuscenes import LidarRecord, NuScenesDataset, load_lidar_points, load_nuscenes
from occdata.nuscenes.rig import RigChoice
from occdata.runtime.lock import store_lock
from occdata.store.build import check_sweep_files
from occdata.store.layout import STATE_DONE, store_rig
from occdata.store.reader import open_store, store_location
from occdata.store.update import update_samples
from occdata.visibility import camera_mask, lidar_mask

__all__ = ["MaskCounts", "SweepRays", "VisibilityReport", "compute_visibility", "points_keyego_from_uvd",
           "sample_visibility"]


@dataclass
class MaskCounts:
    """Voxel counts per class (index 0..17) comparing a computed mask with a shipped one, summed over samples."""

    voxels: np.ndarray = field(default_factory=lambda: np.zeros(NUM_CLASSES, np.int64))
    computed: np.ndarray = field(default_factory=lambda: np.zeros(NUM_CLASSES, np.int64))
    shipped: np.ndarray = field(default_factory=lambda: np.zeros(NUM_CLASSES, np.int64))
    both: np.ndarray = field(default_factory=lambda: np.zeros(NUM_CLASSES, np.int64))

    def add(self, semantics: np.ndarray, computed: np.ndarray, shipped: np.ndarray) -> None:
        sem = np.where(semantics == 255, FREE_LABEL, semantics).reshape(-1).astype(np.int64)
        a, b = computed.reshape(-1) != 0, shipped.reshape(-1) != 0
        self.voxels += np.bincount(sem, minlength=NUM_CLASSES)
        self.computed += np.bincount(sem[a], minlength=NUM_CLASSES)
        self.shipped += np.bincount(sem[b], minlength=NUM_CLASSES)
        self.both += np.bincount(sem[a & b], minlength=NUM_CLASSES)

    def iou(self, classes: np.ndarray | slice = slice(None)) -> float:
        """IoU of the computed and shipped visible sets over the given classes (1.0 if both are empty)."""
        both = self.both[classes].sum()
        union = self.computed[classes].sum() + self.shipped[classes].sum() - both
        return float(both / union) if union else 1.0


@dataclass(frozen=True)
class VisibilityReport:
    computed: int
    skipped_unlabelled: int
    camera: MaskCounts  # over the samples that ship a camera mask (recompute mode), else empty
    lidar: MaskCounts
    compared: int  # samples in `camera` / `lidar`
    seconds_per_sample: float
    free_observed: float = 0.0  # fraction of free voxels in the computed LiDAR masks (all computed samples)


def points_keyego_from_uvd(uvd: np.ndarray, K: np.ndarray, T_keyego_from_cam: np.ndarray) -> np.ndarray:
    """Un-project `(M, 3)` (u, v, depth) of one camera into key ego, `(M, 3) float64`."""
    uvd = np.asarray(uvd, dtype=np.float64)
    rays = np.stack([uvd[:, 0], uvd[:, 1], np.ones(len(uvd))], axis=1) @ np.linalg.inv(K).T
    points_cam = rays * uvd[:, 2:3]
    return points_cam @ T_keyego_from_cam[:3, :3].T + T_keyego_from_cam[:3, 3]


def sample_visibility(
    semantics: np.ndarray,
    K: np.ndarray,
    T_keyego_from_cam: np.ndarray,
    image_size: np.ndarray,
    lidar_origin_keyego: np.ndarray,
    points_keyego: np.ndarray,
    mask_lidar: np.ndarray | None = None,
    grid: OccGrid = GRID,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera mask and LiDAR mask, each `(X, Y, Z) uint8`, on `grid` (a key-ego grid; Occ3D's by default).

    semantics `(X, Y, Z) uint8`; K `(C, 3, 3)`; T_keyego_from_cam `(C, 4, 4)`; image_size `(C, 2)`
    (W, H); lidar_origin_keyego `(3,)`; points_keyego `(M, 3)`. The camera mask is computed within
    `mask_lidar` if given (a shipped one), else within the computed LiDAR mask.
    """
    lower = np.asarray(grid.lower, dtype=np.float64)
    points = np.asarray(points_keyego, dtype=np.float64).reshape(-1, 3)
    origins = np.broadcast_to(np.asarray(lidar_origin_keyego, dtype=np.float64), points.shape)
    lidar = lidar_mask(semantics, origins, points, lower, grid.voxel_size)
    T_cam = np.stack([invert_rigid(np.asarray(T, dtype=np.float64)) for T in T_keyego_from_cam])
    camera = camera_mask(semantics, lidar if mask_lidar is None else mask_lidar, np.asarray(K, np.float64), T_cam,
                         np.asarray(image_size), lower, grid.voxel_size)
    return camera, lidar


@dataclass(frozen=True, eq=False)
class SweepRays:
    """LiDAR rays from the source tree: per store token, every LiDAR's keyframe sweep (the store's rig)
    then up to N previous sweeps of each, each ray from its own LiDAR's origin."""

    dataset: NuScenesDataset
    n_sweeps: int

    @staticmethod
    def load(reader_attrs: dict, root: Path | None, n_sweeps: int) -> SweepRays:
        ident = reader_attrs.get("build_identity", {})
        src = Path(root) if root is not None else Path(ident.get("source_root", ""))
        version = None if root is not None else ident.get("source_version")
        if not src.is_dir():
            raise OccDataError(f"the store's source tree {str(src)!r} is not a folder here; pass --root")
        rig = store_rig(reader_attrs)
        choice = RigChoice(tuple(rig["cameras"]), tuple(rig["lidars"]), rig["reference_lidar"])
        ds = load_nuscenes(src, version, sweeps=n_sweeps > 0, rig=choice)
        rays = SweepRays(ds, n_sweeps)
        check_sweep_files([rays.records(s.token) for s in ds.samples], n_sweeps)
        return rays

    def records(self, token: str) -> tuple[LidarRecord, ...]:
        try:
            i = self.dataset.index_of(token)
        except KeyError:
            where = self.dataset.root
            raise OccDataError(f"sample {token!r} of the store is not in the tables under {where}") from None
        return (*self.dataset.samples[i].lidars, *self.dataset.lidar_histories(i, self.n_sweeps))

    def keyego(self, token: str, T_global_from_keyego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins and end points `(M, 3) float64` in key ego."""
        T_keyego_from_global = invert_rigid(T_global_from_keyego)
        origins, ends = [], []
        for rec in self.records(token):
            T = T_keyego_from_global @ rec.T_global_from_ego @ rec.T_ego_from_lidar
            pts = transform_points(T, load_lidar_points(rec.path)[:, :3].astype(np.float64))
            origins.append(np.broadcast_to(T[:3, 3], pts.shape))
            ends.append(pts)
        return np.concatenate(origins), np.concatenate(ends)


def compute_visibility(
    store: str | Path, recompute: bool = False, block: int = 32, progress: bool = True,
    lidar_sweeps: int | None = None, root: Path | None = None,
) -> VisibilityReport:
    """Masks for labelled samples that ship no camera mask (every labelled sample with `recompute`,
    comparing with the shipped masks per class). With `lidar_sweeps` N, the LiDAR rays come from the
    source tree (`root`, default the store's `build_identity.source_root`): the keyframe sweep and
    up to N previous sweeps; missing sweep files are one error line before anything is written."""
    with store_lock(store_location(store), "visibility"):  # one writer at a time
        return _compute_visibility(store, recompute, block, progress, lidar_sweeps, root)


def _compute_visibility(store: str | Path, recompute: bool, block: int, progress: bool,
                        lidar_sweeps: int | None, root: Path | None) -> VisibilityReport:
    reader = open_store(store)
    if reader.grid.frame is not LabelFrame.KEY_EGO:
        raise OccDataError(f"{store}: its labels are on grid {reader.grid.name} in the LIDAR_TOP frame; occdata "
                           "visibility computes key-ego masks only (not available for this grid)")
    attrs = dict(reader.group.attrs)
    if lidar_sweeps is None and len(store_rig(attrs)["lidars"]) > 1:
        # The stored depth points do not say which LiDAR saw them: several LiDARs' rays are cast from the
        # source tree, each from its own origin.
        lidar_sweeps = 0
    rays = None if lidar_sweeps is None else SweepRays.load(attrs, root, lidar_sweeps)
    group = zarr.open_group(reader.path, mode="r+")
    present = group["labels/present"][:]
    done = reader.state == STATE_DONE
    if not present[done].any():
        raise OccDataError(f"{store}: no labelled samples; visibility needs voxel semantics for occupancy")
    if recompute:
        select = present.copy()
    else:
        has_mask = np.array([bool(present[i]) and bool(group["labels/mask_camera"][i].any())
                             for i in range(reader.n_samples)])
        select = present & ~has_mask & ~group["visibility/present"][:]
    camera_counts, lidar_counts = MaskCounts(), MaskCounts()
    compared = 0

    free_seen = np.zeros(2, np.int64)  # free voxels observed, free voxels

    def fn(a: dict[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
        nonlocal compared
        if rays is None:
            pts = [points_keyego_from_uvd(uvd, a["calib/K"][c], a["calib/T_keyego_from_cam"][c])
                   for c, uvd in enumerate(reader.depth_points(i))]
            origins, ends = a["calib/T_ego_from_lidar"][:3, 3], np.concatenate(pts) if pts else np.zeros((0, 3))
        else:
            origins, ends = rays.keyego(reader.token(i), a["pose/T_global_from_keyego"])
        shipped_lidar = a["labels/mask_lidar"] if a["labels/mask_lidar"].any() else None
        camera, lidar = sample_visibility(
            a["labels/semantics"], a["calib/K"], a["calib/T_keyego_from_cam"], a["cam/image_size"],
            origins, ends, shipped_lidar, reader.grid.grid,
        )
        free = a["labels/semantics"] == FREE_LABEL
        free_seen[:] += (int(lidar[free].sum()), int(free.sum()))
        if a["labels/mask_camera"].any():
            camera_counts.add(a["labels/semantics"], camera, a["labels/mask_camera"])
            lidar_counts.add(a["labels/semantics"], lidar, a["labels/mask_lidar"])
            compared += 1
        return {"visibility/camera": camera, "visibility/lidar": lidar, "visibility/present": np.bool_(True)}

    t0 = time.perf_counter()
    n = update_samples(
        group,
        ("labels/semantics", "labels/mask_camera", "labels/mask_lidar", "calib/K", "calib/T_keyego_from_cam",
         "cam/image_size", "calib/T_ego_from_lidar", "pose/T_global_from_keyego"),
        fn, select, block, "visibility", progress,
    )
    if n:
        group.attrs["visibility_lidar"] = {
            "rays": "stored depth targets (keyframe points inside an image)" if rays is None else
            f"source LIDAR_TOP keyframe sweep + up to {lidar_sweeps} previous sweeps, all points",
            "lidar_sweeps": lidar_sweeps,
        }
    seconds = (time.perf_counter() - t0) / max(n, 1)
    return VisibilityReport(
        computed=n, skipped_unlabelled=int((done & ~present).sum()), camera=camera_counts, lidar=lidar_counts,
        compared=compared, seconds_per_sample=seconds,
        free_observed=float(free_seen[0] / free_seen[1]) if free_seen[1] else 0.0,
    )
