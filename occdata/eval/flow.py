"""Occupancy flow scores of OpenOcc v2: mAVE and OccScore, on RayIoU's rays (no torch).

Definitions (docs/metrics.md, "mAVE and OccScore"; OpenOcc's `ray_metrics.py`, `calc_metrics` and
`main`): a ray is a true positive at 2 m when its predicted first hit has the true first hit's class
and lies within 2 m of it (float32, strict `<`, as RayIoU). For each of the 8 moving classes, AVE =
the mean over its true-positive rays of |flow_pred - flow_gt| (L2 of (vx, vy)), each flow taken at the
first-hit voxel of its own grid; a class without such rays is NaN and skipped. mAVE = the mean of the
AVEs; OccScore = 0.9 RayIoU + 0.1 max(1 - mAVE, 0), RayIoU being the mean over the 3 taus and the
classes (the reference's `np.nanmean(iou_list)`); NaN when mAVE is.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from occdata.constants import CLASS_NAMES, FREE_LABEL, GRID, NUM_CLASSES, OccGrid
from occdata.errors import OccDataError
from occdata.eval.miou import _nanmean
from occdata.eval.rayiou import RAYIOU_TAUS, RayIoUAccumulator, RayIoUResult, first_hit_voxels, ray_counts

__all__ = ["AVE_TAU", "MOVING_CLASSES", "RayFlowAccumulator", "first_hit_voxels", "flow_sums", "occ_score"]

AVE_TAU = 2.0  # metres: the reference scores velocity on the true positives of its 2nd threshold
MOVING_CLASSES: tuple[int, ...] = tuple(CLASS_NAMES.index(n) for n in (
    "car", "truck", "trailer", "bus", "construction_vehicle", "bicycle", "motorcycle", "pedestrian"))


def flow_sums(gt_dist: np.ndarray, gt_cls: np.ndarray, gt_index: np.ndarray, pred_dist: np.ndarray,
              pred_cls: np.ndarray, pred_index: np.ndarray, flow_gt: np.ndarray, flow_pred: np.ndarray,
              tau: float = AVE_TAU, num_classes: int = NUM_CLASSES, free_label: int = FREE_LABEL,
              classes: Sequence[int] = MOVING_CLASSES) -> np.ndarray:
    """One sample's velocity errors, `(2, K) float64`: per class the sum of |flow_pred - flow_gt| (m/s)
    over its true-positive rays at `tau`, and their count; only `classes` are filled.

    Per-ray inputs as `first_hit_voxels` gives them (truth and prediction cast along the same rays);
    `flow_gt`, `flow_pred` `(X, Y, Z, 2)`, each sampled at the first hit of its own grid."""
    gc = np.asarray(gt_cls).ravel().astype(np.int64)
    pc = np.asarray(pred_cls).ravel().astype(np.int64)
    err = np.abs(np.asarray(pred_dist, np.float32).ravel() - np.asarray(gt_dist, np.float32).ravel())
    tp = (gc != free_label) & (gc == pc) & (err < np.float32(tau)) & np.isin(gc, np.asarray(classes))
    gi = np.asarray(gt_index).ravel()[tp]
    pi = np.asarray(pred_index).ravel()[tp]
    fg = np.asarray(flow_gt, np.float64).reshape(-1, 2)[gi]
    fp = np.asarray(flow_pred, np.float64).reshape(-1, 2)[pi]
    e = np.sqrt(((fp - fg) ** 2).sum(axis=1))
    out = np.zeros((2, num_classes), np.float64)
    out[0] = np.bincount(gc[tp], weights=e, minlength=num_classes)
    out[1] = np.bincount(gc[tp], minlength=num_classes)
    return out


def occ_score(rayiou: float, mave: float) -> float:
    """OpenOcc v2's OccScore: 0.9 RayIoU + 0.1 max(1 - mAVE, 0); NaN when either is NaN."""
    if math.isnan(rayiou) or math.isnan(mave):
        return float("nan")
    return 0.9 * rayiou + 0.1 * max(1.0 - mave, 0.0)


def _check_flow(flow: np.ndarray, grid: OccGrid, what: str) -> np.ndarray:
    f = np.asarray(flow)
    if f.shape != (*grid.shape, 2) or f.dtype.kind != "f":
        raise OccDataError(f"{what} flow has shape {f.shape} {f.dtype}, expected {(*grid.shape, 2)} float")
    return f


class RayFlowAccumulator(RayIoUAccumulator):
    """RayIoU plus OpenOcc v2's mAVE and OccScore over a split: one cast per ray serves both.

    `update(gt, pred, origins, flow_gt, flow_pred)`; `flow_state` `(2, K) float64` (error sums, TP
    counts per class) sums across processes like `state`; `result()` fills the flow fields of
    `RayIoUResult`. Samples given without flow only count for RayIoU (use `RayIoUAccumulator` then)."""

    def __init__(self, taus: Sequence[float] = RAYIOU_TAUS, grid: OccGrid = GRID,
                 num_classes: int = NUM_CLASSES, free_label: int = FREE_LABEL) -> None:
        super().__init__(taus, grid, num_classes, free_label)
        self._flow = np.zeros((2, num_classes), np.float64)

    def update(self, gt: np.ndarray, pred: np.ndarray, origins_keyego: np.ndarray,  # type: ignore[override]
               flow_gt: np.ndarray | None = None, flow_pred: np.ndarray | None = None) -> None:
        """Add one sample; `flow_gt`, `flow_pred` `(X, Y, Z, 2)` m/s (both, or neither: RayIoU only)."""
        if flow_gt is None or flow_pred is None:
            super().update(gt, pred, origins_keyego)
            return
        fg, fp = _check_flow(flow_gt, self.grid, "ground truth"), _check_flow(flow_pred, self.grid, "prediction")
        gd, gc, gi, pd, pc, pi = self._pair_hits(gt, pred, origins_keyego)
        self._counts += ray_counts(gd, gc, pd, pc, self.taus, self.num_classes, self.free_label)
        self._flow += flow_sums(gd, gc, gi, pd, pc, pi, fg, fp, AVE_TAU, self.num_classes, self.free_label)
        self.n_samples += 1

    @property
    def flow_state(self) -> np.ndarray:
        """`(2, K) float64` (a copy): per class the sum of velocity errors and the TP-ray count."""
        return self._flow.copy()

    @classmethod
    def from_states(cls, state: np.ndarray, flow_state: np.ndarray,
                    taus: Sequence[float] = RAYIOU_TAUS) -> RayFlowAccumulator:
        base = RayIoUAccumulator.from_state(state, taus)
        acc = cls(taus, num_classes=base.num_classes)
        acc._counts = base._counts
        f = np.asarray(flow_state, np.float64)
        if f.shape != (2, acc.num_classes):
            raise OccDataError(f"flow state must be (2, {acc.num_classes}), got {f.shape}")
        acc._flow = f.copy()
        return acc

    def merge(self, other: RayIoUAccumulator) -> RayFlowAccumulator:
        super().merge(other)
        if isinstance(other, RayFlowAccumulator):
            self._flow += other._flow
        return self

    def result(self) -> RayIoUResult:
        base = super().result()
        with np.errstate(invalid="ignore", divide="ignore"):
            ave = np.where(self._flow[1] > 0, self._flow[0] / np.maximum(self._flow[1], 1), np.nan)
        ave[[k for k in range(self.num_classes) if k not in MOVING_CLASSES]] = np.nan
        sem = [k for k in range(self.num_classes) if k != self.free_label]
        mave = _nanmean(ave[sem])
        return dataclasses.replace(base, ave_per_class=ave[sem], mave=mave, occ_score=occ_score(base.rayiou, mave))
