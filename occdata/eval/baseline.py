"""The image-free baseline: every voxel's most frequent training label, scored on another split.

It is the floor a camera model has to beat: it knows the store's average street layout (road ahead,
buildings at the sides) but nothing of the scene in front of the car. Pure numpy over the store.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occdata.constants import NUM_CLASSES
from occdata.errors import OccDataError
from occdata.eval.metrics import MIoUAccumulator

__all__ = ["BaselineResult", "image_free_baseline"]


@dataclass(frozen=True)
class BaselineResult:
    """mIoU of the per-voxel most frequent training label (fractions; camera mask and no mask) over the
    `samples` labelled samples of the scored split."""

    train_samples: int
    samples: int
    miou_camera_mask: float
    miou_no_mask: float
    per_class_iou_camera_mask: tuple[float, ...]


def image_free_baseline(reader, train_split: str = "train", split: str = "val") -> BaselineResult:  # noqa: ANN001
    """Predict, for every labelled sample of `split`, the per-voxel most frequent label of the training
    split (ties: the lower label) and score it with Occ3D mIoU. `reader`: an open `StoreReader`."""
    train, val = reader.split_indices(train_split, labelled=True), reader.split_indices(split, labelled=True)
    if not len(train) or not len(val):
        raise OccDataError(f"the baseline needs labelled samples in both {train_split!r} ({len(train)}) and "
                           f"{split!r} ({len(val)})")
    sem, cam = reader.array("labels/semantics"), reader.array("labels/mask_camera")
    shape = tuple(sem.shape[1:])
    counts = np.zeros((int(np.prod(shape)), NUM_CLASSES), dtype=np.int32)
    rows = np.arange(counts.shape[0])
    for i in train:
        counts[rows, np.asarray(sem[int(i)]).reshape(-1)] += 1
    pred = counts.argmax(axis=1).astype(np.uint8).reshape(shape)
    masked, unmasked = MIoUAccumulator(), MIoUAccumulator()
    for i in val:
        gt = np.asarray(sem[int(i)])
        masked.update(gt, pred, np.asarray(cam[int(i)]))
        unmasked.update(gt, pred, None)
    m, u = masked.result(), unmasked.result()
    per_class = tuple(float(x) for x in m.per_class_iou)
    return BaselineResult(train_samples=len(train), samples=len(val), miou_camera_mask=float(m.miou),
                          miou_no_mask=float(u.miou), per_class_iou_camera_mask=per_class)
