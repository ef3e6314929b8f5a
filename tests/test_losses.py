"""Loss functions against small cases worked out by hand (the arithmetic is in the comments)."""

from __future__ import annotations

import math

import pytest
import torch

from fastocc.losses import (
    LossConfig,
    LossTargets,
    bev_bce_loss,
    class_weights_from_counts,
    depth_bce_loss,
    dice_loss,
    focal_loss,
    geo_scal_loss,
    lovasz_softmax_loss,
    occupancy_loss,
    sem_scal_loss,
)


def _voxels(rows: list[list[float]]) -> torch.Tensor:
    """Per-voxel class scores `(V, C)` -> logits `(1, C, V, 1, 1)`."""
    return torch.tensor(rows, dtype=torch.float64).T.reshape(1, len(rows[0]), len(rows), 1, 1)


def _labels(values: list[int]) -> torch.Tensor:
    return torch.tensor(values).reshape(1, len(values), 1, 1)


# Two voxels, three classes, free = class 2. Logits are log-probabilities, so softmax gives:
#   voxel a: p = (0.5, 0.25, 0.25), label 0;  voxel b: p = (0.25, 0.5, 0.25), label 2 (free).
SOFT_LOGITS = _voxels(
    [[math.log(0.5), math.log(0.25), math.log(0.25)], [math.log(0.25), math.log(0.5), math.log(0.25)]]
)
SOFT_LABELS = _labels([0, 2])

# Focal case: sigmoid logits; voxel a (0, ln 3, 0) -> p = (0.5, 0.75, 0.5), label 1; voxel b (0, 0, 0), label 0.
FOCAL_LOGITS = _voxels([[0.0, math.log(3.0), 0.0], [0.0, 0.0, 0.0]])
FOCAL_LABELS = _labels([1, 0])
# negative with p = 0.5:  0.75 * 0.5^2 * ln 2           = 0.12996510
# positive with p = 0.75: 0.25 * 0.25^2 * ln(4/3)       = 0.00449503
# positive with p = 0.5:  0.25 * 0.5^2 * ln 2           = 0.04332169
VOXEL_A = 2 * 0.12996510 + 0.00449503  # 0.26442523
VOXEL_B = 0.04332169 + 2 * 0.12996510  # 0.30325189


def test_focal_unweighted_is_mean_over_voxels_of_class_sums() -> None:
    assert float(focal_loss(FOCAL_LOGITS, FOCAL_LABELS)) == pytest.approx((VOXEL_A + VOXEL_B) / 2, abs=1e-7)
    assert float(focal_loss(FOCAL_LOGITS, FOCAL_LABELS)) == pytest.approx(0.28383856, abs=1e-7)


def test_focal_camera_mask_keeps_only_visible_voxels() -> None:
    mask = torch.tensor([True, False]).reshape(1, 2, 1, 1)
    assert float(focal_loss(FOCAL_LOGITS, FOCAL_LABELS, mask)) == pytest.approx(0.26442523, abs=1e-7)


def test_focal_class_weights_scale_each_voxel_by_its_label_weight() -> None:
    w = torch.tensor([2.0, 1.0, 1.0])  # voxel a (label 1) x1, voxel b (label 0) x2: (0.26442523 + 0.60650378) / 2
    assert float(focal_loss(FOCAL_LOGITS, FOCAL_LABELS, class_weights=w)) == pytest.approx(0.43546451, abs=1e-7)


def test_class_weights_from_counts() -> None:
    # 1 / ln(1000.001) = 1 / 6.90775628 = 0.14476483;  1 / ln(e^2) = 0.5
    w = class_weights_from_counts([1000.0, math.e**2 - 0.001])
    assert w.tolist() == pytest.approx([0.14476483, 0.5], abs=1e-6)


def test_sem_scal_hand_case() -> None:
    # class 0 (present): P = 0.5 / 0.75 = 2/3, R = 0.5 / 1 = 1/2, S = 0.75 / 1 = 3/4 -> -ln(1/4) = ln 4
    # class 1 absent -> skipped; class 2 is free -> skipped
    loss = sem_scal_loss(SOFT_LOGITS, SOFT_LABELS, free_label=2)
    assert float(loss) == pytest.approx(1.38629436, abs=1e-6)


def test_geo_scal_hand_case() -> None:
    # p_occ = 1 - p_free = (0.75, 0.75), occupied = (1, 0):
    # P = 0.75 / 1.5 = 1/2, R = 0.75 / 1 = 3/4, S = 0.25 / 1 = 1/4 -> ln 2 + ln(4/3) + ln 4 = ln(32/3)
    loss = geo_scal_loss(SOFT_LOGITS, SOFT_LABELS, free_label=2)
    assert float(loss) == pytest.approx(2.36712361, abs=1e-6)


def test_scal_mask_drops_voxels() -> None:
    # only voxel a kept: class 0 has P = 0.5 / 0.5 = 1, R = 0.5 / 1 = 1/2, no negatives (S skipped) -> ln 2
    mask = torch.tensor([True, False]).reshape(1, 2, 1, 1)
    assert float(sem_scal_loss(SOFT_LOGITS, SOFT_LABELS, mask, free_label=2)) == pytest.approx(0.69314718, abs=1e-6)


def test_dice_hand_case() -> None:
    # class 0: 1 - (2*0.5 + 1) / (0.75 + 1 + 1)  = 3/11
    # class 1: 1 - (0 + 1)     / (0.75 + 0 + 1)  = 3/7
    # class 2: 1 - (2*0.25 + 1) / (0.5 + 1 + 1)  = 2/5      mean = 424/1155 = 0.36709957
    assert float(dice_loss(SOFT_LOGITS, SOFT_LABELS)) == pytest.approx(0.36709957, abs=1e-7)


def test_lovasz_softmax_hand_case() -> None:
    # 3 voxels, 2 classes, p(class 1) = (0.9, 0.6, 0.2), labels (0, 1, 1).
    # class 1: errors (0.9, 0.4, 0.8) sorted 0.9(t=0) 0.8(t=1) 0.4(t=1); gts = 2
    #   J = 1 - (2-cumsum t)/(2+cumsum(1-t)) = (1/3, 2/3, 1) -> grad (1/3, 1/3, 1/3) -> 2.1/3 = 0.7
    # class 0: errors (0.9, 0.4, 0.8) sorted 0.9(t=1) 0.8(t=0) 0.4(t=0); gts = 1
    #   J = (1, 1, 1) -> grad (1, 0, 0) -> 0.9.           mean = 0.8
    p1 = [0.9, 0.6, 0.2]
    logits = _voxels([[math.log(1 - q), math.log(q)] for q in p1])
    assert float(lovasz_softmax_loss(logits, _labels([0, 1, 1]))) == pytest.approx(0.8, abs=1e-7)


def test_depth_bce_hand_case() -> None:
    # pixel 1: p = (0.5, 0.25, 0.25), target bin 0 -> ln 2 + 2 ln(4/3) = 1.26851132; pixel 2 has no target
    probs = torch.tensor([[0.5, 0.25, 0.25], [0.2, 0.3, 0.5]]).T.reshape(1, 3, 1, 2)
    onehot = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]).T.reshape(1, 3, 1, 2)
    assert float(depth_bce_loss(probs, onehot)) == pytest.approx(1.26851132, abs=1e-6)


def test_bev_bce_hand_case() -> None:
    # logits (0, ln 3) -> p = (0.5, 0.75), target (1, 0): (ln 2 + ln 4) / 2 = 1.03972077
    logits = torch.tensor([0.0, math.log(3.0)]).reshape(1, 2, 1, 1)
    target = torch.tensor([1.0, 0.0]).reshape(1, 2, 1, 1)
    assert float(bev_bce_loss(logits, target)) == pytest.approx(1.03972077, abs=1e-6)


def test_combined_loss_weights_and_camera_mask_switch() -> None:
    cfg = LossConfig(focal=0, sem_scal=0, geo_scal=0.5, dice=2.0, lovasz=0, depth=0, bev=0, use_camera_mask=False)
    targets = LossTargets(voxel_labels=SOFT_LABELS)
    # geo_scal uses FREE_LABEL = 17 here, so use an 18-class version of the soft case: pad 15 classes with p = 0
    logits = torch.cat(
        [SOFT_LOGITS[:, :2], torch.full((1, 15, 2, 1, 1), -1e9, dtype=torch.float64), SOFT_LOGITS[:, 2:]], 1
    )
    labels = torch.where(SOFT_LABELS == 2, 17, SOFT_LABELS)
    targets = LossTargets(voxel_labels=labels)
    total, terms = occupancy_loss(logits, targets, cfg)
    assert set(terms) == {"geo_scal", "dice"}
    assert float(terms["geo_scal"]) == pytest.approx(2.36712361, abs=1e-6)
    # dice over 18 classes: the three above plus 15 empty classes with loss 1 - 1/1 = 0 -> (424/385) / 18
    assert float(terms["dice"]) == pytest.approx((424 / 385) / 18, abs=1e-6)
    assert float(total) == pytest.approx(0.5 * 2.36712361 + 2.0 * (424 / 385) / 18, abs=1e-6)
    with pytest.raises(ValueError, match="mask_camera"):
        occupancy_loss(logits, targets, LossConfig(use_camera_mask=True))
