"""Per-stage shapes for every preset and head; nano trains (forward + backward) on CPU without NaN."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from fastocc.losses import LossConfig, LossTargets, occupancy_loss
from fastocc.model import PRESETS, FastOcc, HeadKind, preset, synthetic_inputs
from fastocc.model.heads import FastOccHead


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_stage_shapes_on_meta_device(name: str) -> None:
    cfg = PRESETS[name]
    h, w = cfg.feat_hw
    with torch.device("meta"):
        net = FastOcc(cfg)
        images = torch.empty(1, 6, 3, *cfg.input_hw)
        feat = net.image_stage(images)
        depth, context = net.depth_net(feat)
        bev_map = net.head.decoder(torch.empty(1, cfg.context_channels * 8, 100, 100))
        bev_logits = net.bev_head(bev_map)
    assert feat.shape == (6, cfg.neck_channels, h, w)
    assert depth.shape == (6, 88, h, w) and context.shape == (6, cfg.context_channels, h, w)
    assert bev_map.shape == (1, cfg.bev_channels, 100, 100)
    assert bev_logits.shape == (1, 18, 200, 200)


@pytest.mark.parametrize("head", [HeadKind.FCN3D, HeadKind.DECONV])
def test_baseline_heads_on_meta_device(head: HeadKind) -> None:
    cfg = preset("tiny", head=head)
    with torch.device("meta"):
        net = FastOcc(cfg)
        logits, bev_logits = net.head(None, torch.empty(1, cfg.context_channels * 8, 100, 100), None)
    assert logits.shape == (1, 18, 200, 200, 16) and bev_logits is None
    assert net.bev_head is None


@pytest.mark.parametrize("head", list(HeadKind))
def test_nano_forward_backward_with_all_losses(head: HeadKind) -> None:
    torch.manual_seed(0)
    cfg = preset("nano", head=head)
    net = FastOcc(cfg).train()
    inputs = synthetic_inputs(1, cfg.input_hw)
    out = net(inputs)
    assert out.voxel_logits.shape == (1, 18, 200, 200, 16)
    assert out.depth_probs.shape == (6, 88, 8, 22)
    torch.testing.assert_close(out.depth_probs.sum(1), torch.ones(6, 8, 22))
    assert (out.bev_logits is not None) == (head is HeadKind.FASTOCC)
    if out.bev_logits is not None:
        assert out.bev_logits.shape == (1, 18, 200, 200)
    g = torch.Generator().manual_seed(1)
    targets = LossTargets(
        voxel_labels=torch.randint(0, 18, (1, 200, 200, 16), generator=g),
        mask_camera=torch.rand(1, 200, 200, 16, generator=g) > 0.5,
        depth_onehot=F.one_hot(torch.randint(0, 88, (6, 8, 22), generator=g), 88).permute(0, 3, 1, 2).float(),
        bev_multihot=(torch.rand(1, 18, 200, 200, generator=g) > 0.8).float(),
    )
    total, terms = occupancy_loss(out.voxel_logits, targets, LossConfig(), out.depth_probs, out.bev_logits)
    assert torch.isfinite(total) and len(terms) == (7 if head is HeadKind.FASTOCC else 6)
    total.backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None and not n.startswith("backbone.fc.")]
    assert not missing  # only torchvision's unused classifier gets no gradient
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
    assert float(net.backbone.conv1.weight.grad.abs().sum()) > 0  # the loss reaches the image backbone


def test_eval_mode_skips_bev_head_and_streams_with_temporal_queue() -> None:
    torch.manual_seed(0)
    cfg = preset("nano", num_history=2)
    net = FastOcc(cfg).eval()
    inputs = synthetic_inputs(1, cfg.input_hw)
    with torch.no_grad():
        first = net(inputs)
        second = net(inputs)  # queue now holds frame 1
    assert first.bev_logits is None
    assert second.voxel_logits.shape == (1, 18, 200, 200, 16)
    assert net.temporal is not None and net.temporal._feats is not None
    assert net.temporal._feats.shape == (1, 2, 16 * 8, 100, 100)


def test_factorised_fusion_equals_concat_and_one_1x1x1_conv() -> None:
    torch.manual_seed(0)
    cfg = preset("nano")
    head = FastOccHead(cfg).eval()
    inputs = synthetic_inputs(1, cfg.input_hw)
    feat = torch.randn(6, cfg.neck_channels, 8, 22)
    bev = torch.randn(1, cfg.context_channels * 8, 100, 100)
    with torch.no_grad():
        logits, bev_map = head(feat, bev, inputs)
        # reference: upsample B, repeat along z, sample raw F, concat, Conv3d(k=1), ReLU, classifier
        b_z = F.interpolate(bev_map, size=(200, 200), mode="bilinear", align_corners=False)
        b_z = b_z.unsqueeze(-1).expand(-1, -1, -1, -1, 16)
        p = head.sampler(feat, inputs).permute(0, 4, 1, 2, 3)
        w = torch.cat([head.fuse_bev.weight, head.fuse_img.weight], dim=1).unsqueeze(-1)
        v = F.relu(F.conv3d(torch.cat([b_z, p], dim=1), w, head.fuse_bev.bias))
        ref = F.conv3d(v, head.classifier.weight[..., None, None, None], head.classifier.bias)
    torch.testing.assert_close(logits, ref, atol=1e-4, rtol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["tiny", "small"])
def test_real_forward_large_presets(name: str) -> None:
    cfg = PRESETS[name]
    net = FastOcc(cfg).eval()
    with torch.no_grad():
        out = net(synthetic_inputs(1, cfg.input_hw))
    assert out.voxel_logits.shape == (1, 18, 200, 200, 16)
    assert out.depth_probs.shape == (6, 88, *cfg.feat_hw)
    assert torch.isfinite(out.voxel_logits).all()
