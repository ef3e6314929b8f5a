"""`occdata visibility-check`: recompute one Occ3D label's camera mask with a nuScenes camera rig.

The label's own `semantics` + `mask_lidar` go through `occdata.visibility.camera_mask` with the
cameras of one keyframe of a nuScenes tree (the rig is rigid on the car, so any keyframe of the same
vehicle serves); the result is scored against the label's shipped `mask_camera`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occdata.constants import CLASS_NAMES, FREE_LABEL, GRID
from occdata.errors import OccDataError
from occdata.formats.occ3d import read_label
from occdata.nuscenes.reader import load_nuscenes
from occdata.visibility import MAX_OCCLUDERS, camera_mask

__all__ = ["CheckConfig", "MaskAgreement", "agreement", "check_label", "rig_of_sample"]


@dataclass(frozen=True)
class CheckConfig:
    label: Path
    root: Path
    version: str | None = None
    sample: str | None = None  # sample token; None = the first keyframe
    max_occluders: int = MAX_OCCLUDERS


@dataclass(frozen=True)
class MaskAgreement:
    """IoU of two visible sets overall / on occupied / on free voxels (fractions, 1.0 when both empty),
    and per class (index) the visible fraction in the computed and the shipped mask."""

    iou_all: float
    iou_occupied: float
    iou_free: float
    precision: float  # of the computed visible set
    recall: float  # of the shipped visible set
    visible_fraction: dict[int, tuple[float, float, int]]  # class -> (computed, shipped, voxel count)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = int(np.logical_or(a, b).sum())
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def agreement(semantics: np.ndarray, computed: np.ndarray, shipped: np.ndarray) -> MaskAgreement:
    """Compare two camera masks `(X, Y, Z)` 0/1 over the same semantics `(X, Y, Z) uint8`."""
    a, b = np.asarray(computed) != 0, np.asarray(shipped) != 0
    occ = (semantics != FREE_LABEL) & (semantics != 255)
    both = int((a & b).sum())
    frac = {}
    for c in range(len(CLASS_NAMES)):
        m = semantics == c
        n = int(m.sum())
        if n:
            frac[c] = (float(a[m].mean()), float(b[m].mean()), n)
    return MaskAgreement(
        iou_all=_iou(a, b), iou_occupied=_iou(a & occ, b & occ), iou_free=_iou(a & ~occ, b & ~occ),
        precision=both / max(int(a.sum()), 1), recall=both / max(int(b.sum()), 1), visible_fraction=frac,
    )


def rig_of_sample(root: Path, version: str | None, sample: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cameras of one keyframe in its key-ego frame: K `(6, 3, 3)`, T_cam_from_keyego `(6, 4, 4)`,
    image_size `(6, 2)` (W, H)."""
    ds = load_nuscenes(root, version)
    if not ds.samples:
        raise OccDataError(f"{root}: no keyframe samples")
    if sample is None:
        rec = ds.samples[0]
    else:
        try:
            rec = ds.sample(sample)
        except KeyError:
            raise OccDataError(f"sample {sample!r} not found under {root}") from None
    rig = rec.camera_rig()
    return rig.K, rig.T_cam_from_keyego, rig.image_size


def check_label(config: CheckConfig) -> MaskAgreement:
    """Recompute the label's camera mask with the rig of `config.root` and score it against the label's."""
    label = read_label(config.label, require_masks=True)
    K, T, size = rig_of_sample(config.root, config.version, config.sample)
    computed = camera_mask(label["semantics"], label["mask_lidar"], K, T, size,
                           np.asarray(GRID.lower, np.float64), GRID.voxel_size, config.max_occluders)
    return agreement(label["semantics"], computed, label["mask_camera"])
