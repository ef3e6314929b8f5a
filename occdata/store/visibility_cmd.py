"""`occdata visibility`: camera and LiDAR visibility masks by ray casting (DESIGN §5.3).

Occupancy comes from the stored semantics (label != free), so labelled samples are needed. The
LiDAR rays are the keyframe points stored as depth targets (points inside some camera image),
un-projected exactly into the key-ego frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from occdata.constants import FREE_LABEL, GRID
from occdata.errors import OccDataError
from occdata.geometry import invert_rigid
from occdata.store.layout import STATE_DONE
from occdata.store.lock import store_lock
from occdata.store.reader import open_store
from occdata.store.update import update_samples
from occdata.visibility import camera_visible_mask, lidar_ray_mask

__all__ = ["VisibilityReport", "compute_visibility", "sample_visibility"]


@dataclass(frozen=True)
class VisibilityReport:
    computed: int
    skipped_unlabelled: int
    agreement_iou: dict[int, float]  # sample index -> IoU(computed camera mask, shipped mask_camera)
    seconds_per_sample: float


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
) -> tuple[np.ndarray, np.ndarray]:
    """Camera mask (union over cameras) and LiDAR mask, each `(X, Y, Z) uint8`.

    semantics `(X, Y, Z) uint8`; K `(C, 3, 3)`; T_keyego_from_cam `(C, 4, 4)`; image_size `(C, 2)`
    (W, H); lidar_origin_keyego `(3,)`; points_keyego `(M, 3)`.
    """
    occupied = ((semantics != FREE_LABEL) & (semantics != 255)).astype(np.uint8)
    lower = np.asarray(GRID.lower, dtype=np.float64)
    camera = np.zeros(GRID.shape, dtype=np.uint8)
    for c in range(len(K)):
        T_cam_from_keyego = invert_rigid(np.asarray(T_keyego_from_cam[c], dtype=np.float64))
        camera |= camera_visible_mask(
            occupied, T_cam_from_keyego, np.asarray(K[c], dtype=np.float64),
            int(image_size[c, 0]), int(image_size[c, 1]), lower, GRID.voxel_size,
        )
    origins = np.repeat(np.asarray(lidar_origin_keyego, dtype=np.float64)[None], len(points_keyego), axis=0)
    lidar = lidar_ray_mask(origins, np.asarray(points_keyego, dtype=np.float64), lower, GRID.voxel_size,
                           np.array(GRID.shape, dtype=np.int64))
    return camera, lidar


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def compute_visibility(
    store: Path, recompute: bool = False, block: int = 32, progress: bool = True
) -> VisibilityReport:
    """Masks for labelled samples that have no shipped camera mask (all with `recompute`)."""
    with store_lock(store, "visibility"):  # one writer at a time
        return _compute_visibility(store, recompute, block, progress)


def _compute_visibility(store: Path, recompute: bool, block: int, progress: bool) -> VisibilityReport:
    reader = open_store(store)
    group = zarr.open_group(str(store), mode="r+")
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
    agreement: dict[int, float] = {}

    def fn(a: dict[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
        pts = [points_keyego_from_uvd(uvd, a["calib/K"][c], a["calib/T_keyego_from_cam"][c])
               for c, uvd in enumerate(reader.depth_points(i))]
        camera, lidar = sample_visibility(
            a["labels/semantics"], a["calib/K"], a["calib/T_keyego_from_cam"], a["cam/image_size"],
            a["calib/T_ego_from_lidar"][:3, 3], np.concatenate(pts) if pts else np.zeros((0, 3)),
        )
        if a["labels/mask_camera"].any():
            agreement[i] = _iou(camera, a["labels/mask_camera"])
        return {"visibility/camera": camera, "visibility/lidar": lidar, "visibility/present": np.bool_(True)}

    t0 = time.perf_counter()
    n = update_samples(
        group,
        ("labels/semantics", "labels/mask_camera", "calib/K", "calib/T_keyego_from_cam", "cam/image_size",
         "calib/T_ego_from_lidar"),
        fn, select, block, "visibility", progress,
    )
    seconds = (time.perf_counter() - t0) / max(n, 1)
    return VisibilityReport(
        computed=n, skipped_unlabelled=int((done & ~present).sum()), agreement_iou=agreement,
        seconds_per_sample=seconds,
    )
