"""Occ3D mIoU: one confusion matrix summed over a split, optionally within a visibility mask (no torch).

Definitions are in docs/design.md#metrics and docs/metrics.md. Label grids are `(X, Y, Z) uint8` in key ego
(axis order x, y, z; 17 = free), the Occ3D layout. `MIoUAccumulator` keeps its whole state in one
int64 array (`state`), so ranks/processes can sum it. Values are fractions in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.errors import OccDataError

__all__ = ["MIoUAccumulator", "MIoUResult", "confusion_matrix"]


# --------------------------------------------------------------------------------------------------
# mIoU
# --------------------------------------------------------------------------------------------------
@njit(cache=True)
def _confusion_kernel(gt: np.ndarray, pred: np.ndarray, mask: np.ndarray, use_mask: bool, k: int, free: int,
                      out: np.ndarray) -> None:
    """Add voxel counts to `out (k, k) int64`; flat `gt`, `pred` uint8 (labels < k, checked by the
    caller) and `mask` uint8 0/1. Free/free pairs (most voxels) are summed in a register; only the
    rest goes through the table."""
    tab = np.zeros(k * k, np.int64)
    ff = 0
    for i in range(gt.shape[0]):
        if use_mask and mask[i] == 0:
            continue
        p = pred[i]
        g = gt[i]
        if g == free and p == free:
            ff += 1
        else:
            tab[g * k + p] += 1
    for g in range(k):
        for p in range(k):
            out[g, p] += tab[g * k + p]
    out[free, free] += ff


def _as_labels(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if not np.issubdtype(a.dtype, np.integer):
        raise OccDataError(f"{what} must hold integer class labels, got dtype {a.dtype}")
    if a.size and (a.min() < 0 or a.max() > 255):
        raise OccDataError(f"{what} has labels outside 0..{NUM_CLASSES - 1} (min {a.min()}, max {a.max()})")
    return np.ascontiguousarray(a, dtype=np.uint8)


def confusion_matrix(gt: np.ndarray, pred: np.ndarray, mask: np.ndarray | None = None,
                     num_classes: int = NUM_CLASSES) -> np.ndarray:
    """Confusion matrix `(K, K) int64` (rows = truth, columns = prediction) of two label grids.

    `gt`, `pred`: integer labels of the same shape (any, e.g. `(X, Y, Z)` or `(B, X, Y, Z)`);
    `mask`: same shape, 0/1, voxels with 0 are ignored (None: all voxels). A prediction label
    >= K anywhere, or a truth label >= K inside the mask, raises `OccDataError`.
    """
    g = _as_labels(gt, "ground truth")
    p = _as_labels(pred, "prediction")
    if g.shape != p.shape:
        raise OccDataError(f"prediction shape {p.shape} does not match ground truth shape {g.shape}")
    if mask is None:
        m = np.zeros(1, np.uint8)
    else:
        m = np.ascontiguousarray(mask)
        if m.shape != g.shape:
            raise OccDataError(f"mask shape {m.shape} does not match ground truth shape {g.shape}")
        if m.dtype == np.bool_:
            m = m.view(np.uint8)
        elif m.dtype != np.uint8 or int(m.max(initial=0)) > 1:
            m = (m != 0).astype(np.uint8)
    pmax = int(p.max(initial=0))
    if pmax >= num_classes:
        raise OccDataError(f"prediction has {int((p >= num_classes).sum())} voxels with labels >= {num_classes} "
                           f"(max {pmax}); labels must be 0..{num_classes - 1}")
    if int(g.max(initial=0)) >= num_classes:
        bad = (g >= num_classes) if mask is None else (g >= num_classes) & (m != 0)
        if bad.any():
            raise OccDataError(f"ground truth has {int(bad.sum())} voxels with labels >= {num_classes} "
                               f"(max {int(g[bad].max())}); is the sample labelled?")
        g = np.where(bad, 0, g).astype(np.uint8)  # out-of-range truth only outside the mask: never counted
    out = np.zeros((num_classes, num_classes), np.int64)
    free = FREE_LABEL if FREE_LABEL < num_classes else num_classes - 1
    _confusion_kernel(g.ravel(), p.ravel(), m.ravel(), mask is not None, num_classes, free, out)
    return out


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den as float64 with NaN where den == 0 (0/0: class absent)."""
    num = np.asarray(num, np.float64)
    den = np.asarray(den, np.float64)
    out = np.full(np.broadcast(num, den).shape, np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return out


def _nanmean(a: np.ndarray) -> float:
    a = np.asarray(a, np.float64)
    ok = ~np.isnan(a)
    return float(a[ok].mean()) if ok.any() else float("nan")


@dataclass(frozen=True)
class MIoUResult:
    """mIoU of a split. `per_class_iou (K,) float64` (NaN: class absent from truth and prediction),
    `miou` = mean over the non-free classes that are not NaN, `geo_iou` = IoU of occupied (any
    label != free) vs free, `confusion (K, K) int64` (rows = truth)."""

    per_class_iou: np.ndarray
    miou: float
    geo_iou: float
    confusion: np.ndarray


class MIoUAccumulator:
    """Occ3D mIoU over a split: one confusion matrix, updated per sample or batch, mergeable.

    >>> acc = MIoUAccumulator(); acc.update(gt, pred, mask_camera); acc.result().miou
    """

    def __init__(self, num_classes: int = NUM_CLASSES, free_label: int = FREE_LABEL) -> None:
        self.num_classes = num_classes
        self.free_label = free_label
        self._cm = np.zeros((num_classes, num_classes), np.int64)
        self.n_samples = 0

    def update(self, gt: np.ndarray, pred: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Add one sample `(X, Y, Z)` or a batch `(B, X, Y, Z)` of uint8 labels; `mask` 0/1 or None."""
        cm = confusion_matrix(gt, pred, mask, self.num_classes)
        self._cm += cm
        self.n_samples += 1 if np.ndim(gt) <= 3 else int(np.shape(gt)[0])

    @property
    def state(self) -> np.ndarray:
        """The confusion matrix `(K, K) int64` (a copy); sum states across processes."""
        return self._cm.copy()

    @classmethod
    def from_state(cls, state: np.ndarray, free_label: int = FREE_LABEL) -> MIoUAccumulator:
        state = np.asarray(state)
        if state.ndim != 2 or state.shape[0] != state.shape[1]:
            raise OccDataError(f"mIoU state must be a square confusion matrix, got shape {state.shape}")
        acc = cls(state.shape[0], free_label)
        acc._cm = state.astype(np.int64, copy=True)
        return acc

    def merge(self, other: MIoUAccumulator) -> MIoUAccumulator:
        """Add another accumulator's counts into this one (returns self)."""
        if other._cm.shape != self._cm.shape:
            raise OccDataError("cannot merge mIoU accumulators with different class counts")
        self._cm += other._cm
        self.n_samples += other.n_samples
        return self

    def result(self) -> MIoUResult:
        cm = self._cm
        tp = np.diag(cm)
        iou = _ratio(tp, cm.sum(0) + cm.sum(1) - tp)
        sem = [c for c in range(self.num_classes) if c != self.free_label]
        occ = np.array(sem)
        geo_tp = cm[np.ix_(occ, occ)].sum()
        geo_fp = cm[self.free_label, occ].sum()
        geo_fn = cm[occ, self.free_label].sum()
        geo = float(_ratio(geo_tp, geo_tp + geo_fp + geo_fn))
        return MIoUResult(per_class_iou=iou, miou=_nanmean(iou[sem]), geo_iou=geo, confusion=cm.copy())
