"""The combined `occupancy_loss` (one gather, one softmax, per-class sums, one Lovasz sort) against the
per-term formulas it replaced, applied one by one with the mask: values to 1e-5 relative, and gradients.
In float64: the two sum the same terms in other orders, which float32 rounding could push past 1e-5."""

from __future__ import annotations

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

VOXEL_TERMS = ("focal", "sem_scal", "geo_scal", "dice", "lovasz")


def _reference(logits, targets, cfg, depth, bev):
    """The per-term formulas, each given the mask (the code before the combined loss)."""
    mask = targets.mask_camera if cfg.use_camera_mask else None
    y = targets.voxel_labels
    cw = None if cfg.class_weights is None else torch.tensor(cfg.class_weights)
    terms = {
        "focal": focal_loss(logits, y, mask, cw, cfg.focal_gamma, cfg.focal_alpha),
        "sem_scal": sem_scal_loss(logits, y, mask),
        "geo_scal": geo_scal_loss(logits, y, mask),
        "dice": dice_loss(logits, y, mask),
        "lovasz": lovasz_softmax_loss(logits, y, mask),
        "depth": depth_bce_loss(depth, targets.depth_onehot),
        "bev": bev_bce_loss(bev, targets.bev_multihot),
    }
    total = sum(getattr(cfg, k) * v for k, v in terms.items())
    return total, terms


def _case(seed: int, shape=(2, 18, 12, 10, 4), missing=(3, 9), scale=3.0):
    """Random logits, labels skewed to free (17) with some classes absent, a ~30% mask, depth and BEV."""
    g = torch.Generator().manual_seed(seed)
    B, C, X, Y, Z = shape
    logits = (torch.randn(shape, generator=g, dtype=torch.float64) * scale).requires_grad_()
    probs = torch.full((C,), 1.0)
    probs[17] = 12.0
    for c in missing:
        probs[c] = 0.0
    labels = torch.multinomial(probs, B * X * Y * Z, replacement=True, generator=g).reshape(B, X, Y, Z)
    mask = torch.rand((B, X, Y, Z), generator=g) < 0.3
    depth_logits = torch.randn(B * 6, 88, 4, 6, generator=g, dtype=torch.float64).requires_grad_()
    k = torch.randint(0, 88, (B * 6, 4, 6), generator=g)
    onehot = torch.nn.functional.one_hot(k, 88).permute(0, 3, 1, 2).double()
    onehot[:, :, 0, :] = 0  # rows without a depth target
    bev = torch.randn(B, 18, 8, 8, generator=g, dtype=torch.float64).requires_grad_()
    bev_t = (torch.rand(B, 18, 8, 8, generator=g) < 0.2).double()
    targets = LossTargets(voxel_labels=labels, mask_camera=mask, depth_onehot=onehot, bev_multihot=bev_t)
    return logits, depth_logits, bev, targets


@pytest.mark.parametrize("use_mask", [True, False])
@pytest.mark.parametrize("weighted", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_combined_loss_equals_the_per_term_formulas_values_and_gradients(use_mask, weighted, seed):
    logits, depth_logits, bev, targets = _case(seed)
    cw = tuple(float(w) for w in class_weights_from_counts(torch.arange(1, 19) * 1000.0)) if weighted else None
    cfg = LossConfig(use_camera_mask=use_mask, class_weights=cw, lovasz=0.7, dice=1.3)

    def run(fn):
        for t in (logits, depth_logits, bev):
            t.grad = None
        depth = depth_logits.softmax(dim=1)
        total, terms = fn(logits, targets, cfg, depth, bev)
        total.backward()
        grads = [t.grad.clone() for t in (logits, depth_logits, bev)]
        return float(total.detach()), {k: float(v.detach()) for k, v in terms.items()}, grads

    ref_total, ref_terms, ref_grads = run(_reference)
    got_total, got_terms, got_grads = run(occupancy_loss)
    assert set(got_terms) == set(ref_terms)
    for k in ref_terms:
        assert got_terms[k] == pytest.approx(ref_terms[k], rel=1e-5, abs=1e-7), k
    assert got_total == pytest.approx(ref_total, rel=1e-5)
    for got, ref in zip(got_grads, ref_grads, strict=True):
        scale = float(ref.abs().max())
        assert scale > 0
        assert float((got - ref).abs().max()) <= 1e-5 * scale + 1e-9
    if use_mask:  # masked-out voxels get no gradient
        assert float(got_grads[0].movedim(1, -1)[~targets.mask_camera].abs().max()) == 0.0


@pytest.mark.parametrize("term", VOXEL_TERMS)
def test_each_voxel_term_alone_matches_its_formula(term):
    logits, depth_logits, bev, targets = _case(7, scale=1.0)
    weights = {k: (1.0 if k == term else 0.0) for k in (*VOXEL_TERMS, "depth", "bev")}
    cfg = LossConfig(use_camera_mask=True, **weights)
    total, terms = occupancy_loss(logits, targets, cfg)
    assert set(terms) == {term}
    ref, _ = _reference(logits, targets, cfg, depth_logits.softmax(1), bev)
    assert float(total) == pytest.approx(float(ref), rel=1e-5)


def test_empty_mask_gives_zero_voxel_terms_with_a_gradient_path():
    logits, _, _, targets = _case(3)
    empty = LossTargets(voxel_labels=targets.voxel_labels, mask_camera=torch.zeros_like(targets.mask_camera))
    total, terms = occupancy_loss(logits, empty, LossConfig(depth=0, bev=0))
    assert float(total) == 0.0 and set(terms) == set(VOXEL_TERMS)
    total.backward()
    assert float(logits.grad.abs().max()) == 0.0


def test_only_free_present_matches_the_formulas():
    """No non-free class in the kept voxels: sem_scal has no class (0), geo_scal has no positives."""
    logits, depth_logits, bev, targets = _case(4)
    free = LossTargets(voxel_labels=torch.full_like(targets.voxel_labels, 17), mask_camera=targets.mask_camera,
                       depth_onehot=targets.depth_onehot, bev_multihot=targets.bev_multihot)
    cfg = LossConfig()
    got, got_terms = occupancy_loss(logits, free, cfg, depth_logits.softmax(1), bev)
    ref, ref_terms = _reference(logits, free, cfg, depth_logits.softmax(1), bev)
    for k in ref_terms:
        assert float(got_terms[k]) == pytest.approx(float(ref_terms[k]), rel=1e-5, abs=1e-7), k
