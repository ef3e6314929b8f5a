"""Occupancy losses (docs/design.md#losses), each a pure function of tensors, plus a configurable combined loss.

Shapes: voxel logits `(B, C, X, Y, Z)` (C = 18 incl. free), labels `(B, X, Y, Z) int64`, optional camera
mask `(B, X, Y, Z) bool`. Every voxel loss accepts the mask; voxels with mask False do not contribute.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from occdata.constants import FREE_LABEL

__all__ = [
    "LossConfig",
    "LossTargets",
    "bev_bce_loss",
    "class_weights_from_counts",
    "depth_bce_loss",
    "dice_loss",
    "focal_loss",
    "geo_scal_loss",
    "lovasz_softmax_loss",
    "occupancy_loss",
    "sem_scal_loss",
]

_EPS = 1e-7


def class_weights_from_counts(counts: Sequence[float] | Tensor) -> Tensor:
    """w_c = 1 / ln(f_c + 0.001) with f_c the voxel COUNT of class c over the training set (counts, not
    fractions: a fraction < 1 would give a negative weight). Returns `(C,) float32`."""
    f = torch.as_tensor(counts, dtype=torch.float64)
    return (1.0 / torch.log(f + 0.001)).float()


def _flatten(logits: Tensor, labels: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """-> logits `(V, C)` and labels `(V,)` of the voxels kept by the mask."""
    C = logits.shape[1]
    flat = logits.movedim(1, -1).reshape(-1, C)
    labels = labels.reshape(-1)
    if mask is not None:
        keep = mask.reshape(-1).bool()
        flat, labels = flat[keep], labels[keep]
    return flat, labels


def focal_loss(
    logits: Tensor,
    labels: Tensor,
    mask: Tensor | None = None,
    class_weights: Tensor | None = None,
    gamma: float = 2.0,
    alpha: float = 0.25,
) -> Tensor:
    """Sigmoid focal loss over C one-vs-all classes.

    Per voxel v and class c with p = sigmoid(x_vc), t = [y_v = c]:
    FL = -alpha (1-p)^gamma ln p if t else -(1-alpha) p^gamma ln(1-p). A voxel's loss is the sum over c,
    times w_{y_v} when class weights are given; the result is the mean over the kept voxels.
    """
    x, y = _flatten(logits, labels, mask)
    if x.shape[0] == 0:
        return logits.sum() * 0.0
    t = F.one_hot(y, x.shape[1]).to(x.dtype)
    p = torch.sigmoid(x)
    ce = F.binary_cross_entropy_with_logits(x, t, reduction="none")  # -ln p or -ln(1-p), stable
    p_t = p * t + (1 - p) * (1 - t)
    alpha_t = alpha * t + (1 - alpha) * (1 - t)
    per_voxel = (alpha_t * (1 - p_t) ** gamma * ce).sum(dim=1)
    if class_weights is not None:
        per_voxel = per_voxel * class_weights.to(x)[y]
    return per_voxel.mean()


def _scal_terms(p: Tensor, t: Tensor) -> Tensor:
    """-ln precision - ln recall - ln specificity for probabilities p and binary targets t `(V,)`,
    skipping a term whose denominator is 0."""
    loss = p.new_zeros(())
    tp = (p * t).sum()
    if p.sum() > 0:
        loss = loss - torch.log((tp / p.sum()).clamp_min(_EPS))
    if t.sum() > 0:
        loss = loss - torch.log((tp / t.sum()).clamp_min(_EPS))
    neg = 1 - t
    if neg.sum() > 0:
        loss = loss - torch.log((((1 - p) * neg).sum() / neg.sum()).clamp_min(_EPS))
    return loss


def sem_scal_loss(logits: Tensor, labels: Tensor, mask: Tensor | None = None, free_label: int = FREE_LABEL) -> Tensor:
    """MonoScene semantic scene-class affinity: mean over the non-free classes present in the (kept) labels
    of -ln P_c - ln R_c - ln S_c on the softmax probabilities."""
    x, y = _flatten(logits, labels, mask)
    p = x.softmax(dim=1)
    total, count = x.new_zeros(()), 0
    for c in range(x.shape[1]):
        if c == free_label:
            continue
        t = (y == c).to(p.dtype)
        if t.sum() == 0:
            continue
        total = total + _scal_terms(p[:, c], t)
        count += 1
    return total / max(count, 1)


def geo_scal_loss(logits: Tensor, labels: Tensor, mask: Tensor | None = None, free_label: int = FREE_LABEL) -> Tensor:
    """Geometric scene-class affinity: the three terms (summed) on p_occ = 1 - p_free vs y != free."""
    x, y = _flatten(logits, labels, mask)
    p_occ = 1 - x.softmax(dim=1)[:, free_label]
    return _scal_terms(p_occ, (y != free_label).to(p_occ.dtype))


def dice_loss(logits: Tensor, labels: Tensor, mask: Tensor | None = None, smooth: float = 1.0) -> Tensor:
    """Mean over all C classes of 1 - (2 sum(p t) + 1) / (sum p + sum t + 1), p = softmax."""
    x, y = _flatten(logits, labels, mask)
    p = x.softmax(dim=1)
    t = F.one_hot(y, x.shape[1]).to(p.dtype)
    dice = (2 * (p * t).sum(0) + smooth) / (p.sum(0) + t.sum(0) + smooth)
    return (1 - dice).mean()


def _lovasz_grad(gt_sorted: Tensor) -> Tensor:
    """Gradient of the Lovasz extension of the Jaccard loss w.r.t. sorted errors (Berman et al. 2018)."""
    gts = gt_sorted.sum()
    intersection = gts - gt_sorted.cumsum(0)
    union = gts + (1 - gt_sorted).cumsum(0)
    jaccard = 1 - intersection / union
    jaccard[1:] = jaccard[1:] - jaccard[:-1].clone()
    return jaccard


def lovasz_softmax_loss(logits: Tensor, labels: Tensor, mask: Tensor | None = None) -> Tensor:
    """Lovasz-softmax, averaged over the classes present in the (kept) labels."""
    x, y = _flatten(logits, labels, mask)
    p = x.softmax(dim=1)
    losses = []
    for c in range(x.shape[1]):
        t = (y == c).to(p.dtype)
        if t.sum() == 0:
            continue
        errors = (t - p[:, c]).abs()
        errors_sorted, order = torch.sort(errors, descending=True)
        losses.append(torch.dot(errors_sorted, _lovasz_grad(t[order])))
    return torch.stack(losses).mean() if losses else logits.sum() * 0.0


def depth_bce_loss(depth_probs: Tensor, depth_onehot: Tensor) -> Tensor:
    """BCE between the predicted depth distribution and the one-hot bin target, `(B', D, h, w)` each.

    Summed over the D bins, averaged over the pixels that have a target (an all-zero row = no target).
    """
    D = depth_probs.shape[1]
    p = depth_probs.movedim(1, -1).reshape(-1, D)
    t = depth_onehot.movedim(1, -1).reshape(-1, D).to(p.dtype)
    has_target = t.sum(dim=1) > 0
    if not bool(has_target.any()):
        return depth_probs.sum() * 0.0
    bce = F.binary_cross_entropy(p[has_target].clamp(_EPS, 1 - _EPS), t[has_target], reduction="sum")
    return bce / has_target.sum()


def bev_bce_loss(bev_logits: Tensor, bev_multihot: Tensor) -> Tensor:
    """Mean BCE-with-logits on the multi-hot BEV target `(B, M, 200, 200)` (M = 18, free is channel 17)."""
    return F.binary_cross_entropy_with_logits(bev_logits, bev_multihot.to(bev_logits.dtype))


@dataclass(frozen=True)
class LossTargets:
    """Targets of one batch.

    voxel_labels `(B, 200, 200, 16) int64`; mask_camera `(B, 200, 200, 16) bool` or None;
    depth_onehot `(B*N, 88, h, w) float32` or None; bev_multihot `(B, 18, 200, 200) float32` or None.
    """

    voxel_labels: Tensor
    mask_camera: Tensor | None = None
    depth_onehot: Tensor | None = None
    bev_multihot: Tensor | None = None


@dataclass(frozen=True)
class LossConfig:
    """Weights of the terms of the total loss (0 disables a term) and the camera-mask switch.

    use_camera_mask: when True only voxels with mask_camera = 1 enter the voxel losses. This matches the
    Occ3D evaluation and inflates voxel mIoU by 10+ points, while RayIoU (no mask) barely moves; when
    False the network is also trained on voxels no camera sees.
    """

    focal: float = 1.0
    sem_scal: float = 1.0
    geo_scal: float = 1.0
    dice: float = 1.0
    lovasz: float = 1.0
    depth: float = 1.0
    bev: float = 1.0
    use_camera_mask: bool = True
    class_weights: tuple[float, ...] | None = None  # w_c per class, e.g. from class_weights_from_counts
    focal_gamma: float = 2.0
    focal_alpha: float = 0.25


def _gather_voxels(logits: Tensor, labels: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """-> logits `(V, C)` and labels `(V,)` of the kept voxels, selected once for all the voxel terms
    (autograd then scatters one masked gradient back instead of one per term)."""
    C = logits.shape[1]
    flat = logits.movedim(1, -1).reshape(-1, C)  # a view when the logits are channels-last underneath
    if mask is None:
        return flat, labels.reshape(-1)
    # index_select: its backward is an index_add, ~3x cheaper on CPU than boolean indexing's index_put
    keep = torch.nonzero(mask.reshape(-1)).squeeze(1)
    return flat.index_select(0, keep), labels.reshape(-1).index_select(0, keep)


def _scal_vectorised(tp: Tensor, p_sum: Tensor, t_sum: Tensor, n: int) -> Tensor:
    """`_scal_terms` for K problems at once from their sufficient statistics `(K,)`: sum(p t), sum(p),
    sum(t) over n voxels. A term whose denominator is 0 is skipped (0), as in `_scal_terms`."""
    neg = n - t_sum  # sum(1 - t)
    tn = neg - (p_sum - tp)  # sum((1 - p)(1 - t))
    terms = (
        (p_sum > 0, tp, p_sum),  # precision
        (t_sum > 0, tp, t_sum),  # recall
        (neg > 0, tn, neg),  # specificity
    )
    loss = tp.new_zeros(tp.shape)
    for ok, num, den in terms:
        ratio = (num / torch.where(ok, den, torch.ones_like(den))).clamp_min(_EPS)
        loss = loss - torch.where(ok, torch.log(ratio), torch.zeros_like(ratio))
    return loss


def _lovasz_sorted(p: Tensor, y: Tensor, present: Tensor) -> Tensor:
    """Lovasz-softmax over the present classes with ONE sort: p `(V, C)`, y `(V,)`, present `(C,) bool`.

    After a class's last positive in error order the Jaccard term stays 1, so every later voxel has
    gradient 0 and adds 0: only the positives and the negatives whose error reaches the smallest positive
    error are sorted (same value and gradient; early in training that is a few percent of the voxels).
    All classes go into one sort on the key 2 k + (1 - error) (class k, error descending within it).
    """
    cls = torch.nonzero(present).squeeze(1)
    if cls.numel() == 0:
        return p.sum() * 0.0
    K, V = cls.numel(), p.shape[0]
    gt = y[None, :] == cls[:, None]  # (K, V)
    errors = (gt.to(p.dtype) - p.t()[cls]).abs()
    e = errors.detach()
    smallest_positive = torch.where(gt, e, torch.full_like(e, float("inf"))).amin(1, keepdim=True)
    row, col = torch.nonzero(gt | (e >= smallest_positive), as_tuple=True)  # grouped by class
    key = row.double() * 2 + (1 - e[row, col].double())
    # numpy's vectorised argsort is ~3x torch.sort here; the loss is the same for any order of ties.
    order = torch.from_numpy(np.argsort(key.cpu().numpy())).to(p.device)
    row, flat = row[order], (row * V + col)[order]
    errors_sorted = errors.reshape(-1)[flat]
    gt_sorted = gt.reshape(-1)[flat].to(p.dtype)
    counts = torch.bincount(row, minlength=K)
    start = (torch.cumsum(counts, 0) - counts)[row]  # position of each entry's class block
    first = torch.arange(len(row), device=p.device) == start

    def within(x: Tensor) -> Tensor:  # cumulative sum restarted at every class block
        c = x.cumsum(0)
        return c - torch.where(start > 0, c[(start - 1).clamp_min(0)], torch.zeros_like(c))

    gts = gt.sum(1).to(p.dtype)[row]
    jaccard = 1 - (gts - within(gt_sorted)) / (gts + within(1 - gt_sorted))
    grad = jaccard - torch.where(first, torch.zeros_like(jaccard), jaccard.roll(1))
    per_class = p.new_zeros(K).index_add(0, row, errors_sorted * grad)
    return per_class.mean()


class _FocalSum(torch.autograd.Function):
    """sum_v w_v sum_c alpha_t (1 - p_t)^gamma (-ln p_t) on flat logits `(V, C)` with a hand-written
    backward (autograd's graph of this expression held ~8 full-size temporaries and as many kernels).

    With s = x where t else -x: 1 - p_t = q = sigmoid(-s), -ln p_t = softplus(-s), and
    d/ds [alpha_t q^gamma softplus(-s)] = -alpha_t q^gamma (gamma (1 - q) softplus(-s) + q).
    """

    @staticmethod
    def forward(ctx, x: Tensor, is_t: Tensor, w_v: Tensor, gamma: float, alpha: float) -> Tensor:  # noqa: ANN001
        s = torch.where(is_t, x, -x)
        q, ce = torch.sigmoid(-s), F.softplus(-s)
        alpha_t = torch.where(is_t, x.new_tensor(alpha), x.new_tensor(1 - alpha))
        ctx.save_for_backward(q, ce, is_t, w_v)
        ctx.gamma, ctx.alpha = gamma, alpha
        return ((alpha_t * _pow(q, gamma) * ce).sum(1) * w_v).sum()

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None, None, None]:  # noqa: ANN001
        q, ce, is_t, w_v = ctx.saved_tensors
        d = torch.where(is_t, q.new_tensor(-ctx.alpha), q.new_tensor(1 - ctx.alpha))  # -alpha_t * ds/dx
        d = d * _pow(q, ctx.gamma) * (ctx.gamma * (1 - q) * ce + q)
        return d * (w_v * grad)[:, None], None, None, None, None


def _pow(q: Tensor, gamma: float) -> Tensor:
    return q * q if gamma == 2.0 else q.pow(gamma)


def _focal_fast(x: Tensor, is_t: Tensor, y: Tensor, cw: Tensor | None, gamma: float, alpha: float) -> Tensor:
    """`focal_loss` on flat voxels `(V, C)` (mean over voxels, times w_{y_v} when class weights are given)."""
    w_v = torch.full((x.shape[0],), 1.0 / x.shape[0], dtype=x.dtype, device=x.device)
    if cw is not None:
        w_v = w_v * cw.to(x)[y]
    return _FocalSum.apply(x, is_t, w_v, float(gamma), float(alpha))


def _voxel_terms(x: Tensor, y: Tensor, cfg: LossConfig, free_label: int = FREE_LABEL) -> dict[str, Tensor]:
    """The enabled voxel terms (focal, sem_scal, geo_scal, dice, lovasz) of flat logits `(V, C)` and labels
    `(V,) int64`. Same values as the per-term functions above, from one softmax and shared per-class sums
    (sum p, sum t, sum p t), so the classes are handled at once instead of in Python loops."""
    V, C = x.shape
    names = [k for k in ("focal", "sem_scal", "geo_scal", "dice", "lovasz") if getattr(cfg, k)]
    if V == 0:
        return {k: x.sum() * 0.0 for k in names}
    terms: dict[str, Tensor] = {}
    if cfg.focal:
        cw = None if cfg.class_weights is None else torch.tensor(cfg.class_weights)
        terms["focal"] = _focal_fast(x, F.one_hot(y, C).bool(), y, cw, cfg.focal_gamma, cfg.focal_alpha)
    if names == ["focal"] or not names:
        return terms
    p = x.softmax(dim=1)
    t_sum = torch.bincount(y, minlength=C).to(p.dtype)  # voxels per class
    p_sum = p.sum(0)
    tp = p.new_zeros(C).index_add(0, y, p.gather(1, y[:, None]).squeeze(1))  # sum of p_c over class-c voxels
    present = t_sum > 0
    if cfg.sem_scal:
        keep = present.clone()
        keep[free_label] = False
        terms["sem_scal"] = (_scal_vectorised(tp, p_sum, t_sum, V) * keep).sum() / keep.sum().clamp_min(1)
    if cfg.geo_scal:  # p_occ = 1 - p_free against t = (y != free), from the free class's sums
        n_occ = V - t_sum[free_label]
        tp_occ = n_occ - (p_sum[free_label] - tp[free_label])
        terms["geo_scal"] = _scal_vectorised(tp_occ, V - p_sum[free_label], n_occ, V)
    if cfg.dice:
        terms["dice"] = (1 - (2 * tp + 1.0) / (p_sum + t_sum + 1.0)).mean()
    if cfg.lovasz:
        terms["lovasz"] = _lovasz_sorted(p, y, present)
    return terms


def occupancy_loss(
    voxel_logits: Tensor,
    targets: LossTargets,
    cfg: LossConfig,
    depth_probs: Tensor | None = None,
    bev_logits: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Weighted sum of the enabled terms. Returns (total, {term name: unweighted detached value})."""
    mask = targets.mask_camera if cfg.use_camera_mask else None
    if cfg.use_camera_mask and mask is None:
        raise ValueError("use_camera_mask=True but the targets carry no mask_camera")
    x, y = _gather_voxels(voxel_logits, targets.voxel_labels, mask)
    terms = _voxel_terms(x, y, cfg)
    if cfg.depth and depth_probs is not None and targets.depth_onehot is not None:
        terms["depth"] = depth_bce_loss(depth_probs, targets.depth_onehot)
    if cfg.bev and bev_logits is not None and targets.bev_multihot is not None:
        terms["bev"] = bev_bce_loss(bev_logits, targets.bev_multihot)
    total = sum((getattr(cfg, name) * value for name, value in terms.items()), voxel_logits.new_zeros(()))
    return total, {k: v.detach() for k, v in terms.items()}
