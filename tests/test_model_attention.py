"""The attention view transform (`view_transform = "attention"`, the paper's SurroundOcc* row): reference
points where a hand computation puts them, the image reaches only the voxels a camera sees, every parameter
trains with the deconv head, checkpoints / train config / CLI carry the switch, and the ONNX export matches."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from fastocc.checkpoint import load_model, model_config_to_dict, save_checkpoint
from fastocc.model import FastOcc, preset, synthetic_inputs
from fastocc.model.attention import attention_geometry
from fastocc.train.config import ConfigError, TrainConfig


def _cfg(**kw: object):  # noqa: ANN202
    return preset("nano", input_hw=(96, 256), view_transform="attention", head="deconv", **kw)


def test_reference_point_of_a_voxel_in_the_front_camera_by_hand() -> None:
    """Coarse voxel (75, 50, 1): centre (20.4, 0.4, 0.2) m. Front camera (yaw 0) at (2, 0, 1.6): the point is
    (18.4, 0.4, -1.4) ahead -> camera (x right, y down, z fwd) = (-0.4, 1.4, 18.4); K (f 1260, c 800/450):
    pixel (772.61, 545.87); resize 0.16 and bottom crop to 96 x 256: (123.62, 39.34); stride-16 cells with
    centres at 16 c + 7.5: (7.2260, 1.9900); grid_sample (align_corners False): ((x + 0.5) / 16 * 2 - 1,
    (y + 0.5) / 6 * 2 - 1)."""
    cfg = _cfg()
    geo = attention_geometry(synthetic_inputs(1, cfg.input_hw), cfg, cfg.feat_hw)
    q = (75 * 100 + 50) * 8 + 1
    u, v = 1260 * -0.4 / 18.4 + 800, 1260 * 1.4 / 18.4 + 450
    u, v = 0.16 * u, 0.16 * v + (96 - 900 * 0.16)
    fx, fy = (u - 7.5) / 16, (v - 7.5) / 16
    want = torch.tensor([(fx + 0.5) / 16 * 2 - 1, (fy + 0.5) / 6 * 2 - 1])
    front, back = 1, 4  # synthetic ring yaws (60, 0, -60, 120, 180, -120)
    slot = torch.nonzero((geo.query[front] == q) & (geo.valid[front] == 1)).flatten()
    assert slot.numel() == 1 and int(geo.target[front, slot]) == q
    torch.testing.assert_close(geo.ref[front, slot[0]], want, atol=1e-4, rtol=0)
    assert not bool(((geo.query[back] == q) & (geo.valid[back] == 1)).any())  # behind the back camera
    assert geo.count[0, q] >= 1
    # slots list each camera's seen voxels once, in grid order; padding points at the discarded row
    for n in range(6):
        real = geo.query[n][geo.valid[n] == 1]
        assert torch.equal(real, torch.sort(real).values) and real.unique().numel() == real.numel()
        assert bool((geo.target[n][geo.valid[n] == 0] == 100 * 100 * 8).all())
    assert torch.equal(geo.count[0], torch.bincount(geo.target[geo.valid == 1], minlength=80000).clamp_min(1).float())


def test_image_reaches_only_the_voxels_a_camera_sees() -> None:
    torch.manual_seed(0)
    cfg = _cfg()
    net = FastOcc(cfg).eval()
    a, b = synthetic_inputs(1, cfg.input_hw, seed=1), synthetic_inputs(1, cfg.input_hw, seed=2)
    with torch.no_grad():
        va = net.attention(net.image_stage(a.images), a)
        vb = net.attention(net.image_stage(b.images), b)
    geo = attention_geometry(a, cfg, cfg.feat_hw)
    seen = torch.zeros(100 * 100 * 8, dtype=torch.bool)
    seen[geo.target[geo.valid == 1]] = True
    seen = seen.view(100, 100, 8)
    assert va.shape == (1, cfg.context_channels, 100, 100, 8)
    assert 0 < int((~seen).sum()) and int(seen.sum()) > 0.5 * seen.numel()
    diff = (va - vb).abs().amax(dim=1)[0]  # (100, 100, 8)
    assert float(diff[~seen].max()) == 0.0  # the query alone where no camera looks
    assert float(diff[seen].max()) > 1e-3


def test_attention_with_the_deconv_head_trains_every_parameter() -> None:
    torch.manual_seed(0)
    cfg = _cfg()
    net = FastOcc(cfg).train()
    assert net.depth_net is None and net.pooling is None and net.attention is not None
    out = net(synthetic_inputs(1, cfg.input_hw))
    assert out.depth_probs is None and out.voxel_logits.shape == (1, 18, 200, 200, 16)
    out.voxel_logits.square().mean().backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None and not n.startswith("backbone.fc.")]
    assert not missing
    assert float(net.attention.offsets.weight.grad.abs().sum()) > 0  # the deformable offsets learn


def test_config_checkpoint_train_config_and_cli_carry_the_switch(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ValueError, match="attention_heads"):
        preset("nano", view_transform="attention", attention_heads=3)  # C2 = 16 is not divisible by 3
    cfg = _cfg()
    torch.manual_seed(0)
    model, ckpt = load_model(save_checkpoint(tmp_path / "a.pt", cfg, FastOcc(cfg).state_dict()))
    assert ckpt.model_config == cfg and model.attention is not None
    old_cfg = preset("nano")
    path = save_checkpoint(tmp_path / "old.pt", old_cfg, FastOcc(old_cfg).state_dict())
    payload = torch.load(path, weights_only=True)
    old = model_config_to_dict(old_cfg)
    for k in ("view_transform", "attention_heads", "attention_points"):
        del old[k]
    payload["model_config"] = json.dumps(old)
    torch.save(payload, path)
    assert load_model(path)[1].model_config.view_transform.value == "lss"
    assert TrainConfig(view_transform="attention", head="deconv").model_config().view_transform.value == "attention"
    with pytest.raises(ConfigError, match="view_transform"):
        TrainConfig(view_transform="mlp")

    from click.testing import CliRunner

    import fastocc.train as train_pkg
    from cli.fastocc_cli import main

    seen: list[TrainConfig] = []

    def fake_train(cfg: TrainConfig, resume: bool, progress: bool):  # noqa: ANN202
        seen.append(cfg)
        raise SystemExit(0)

    monkeypatch.setattr(train_pkg, "train", fake_train)
    res = CliRunner().invoke(main, ["train", "--view-transform", "attention", "--head", "deconv", "--out", "x"])
    assert res.exit_code == 0, res.output
    assert (seen[0].view_transform, seen[0].head) == ("attention", "deconv")


def test_export_parity_attention_deconv(tmp_path: Path) -> None:
    """GridSample in the graph, standard operators only, ONNX Runtime matches PyTorch."""
    pytest.importorskip("onnxruntime")
    import onnx

    from fastocc.deploy import ExportConfig, export_onnx
    from fastocc.deploy.export import custom_domain_ops

    torch.manual_seed(0)
    cfg = _cfg()
    ckpt = save_checkpoint(tmp_path / "c.pt", cfg, FastOcc(cfg).state_dict())
    rep = export_onnx(ExportConfig(checkpoint=ckpt, out=tmp_path / "m.onnx", frames=2))
    assert rep.parity.passed and rep.parity.max_abs_diff <= 1e-3 and rep.parity.min_agreement >= 0.999
    assert custom_domain_ops(rep.out) == []
    assert "GridSample" in {n.op_type for n in onnx.load(str(rep.out)).graph.node}


@torch.no_grad()
def test_sampling_only_seen_pairs_equals_the_dense_computation() -> None:
    """Reference: every voxel sampled in every camera (grid_sample over all Q), masked by visibility and
    averaged over the cameras that see it; the module samples only the seen (voxel, camera) slots."""
    import torch.nn.functional as F

    from fastocc.model.geometry import project_points_to_feature, voxel_centres

    torch.manual_seed(0)
    cfg = _cfg()
    att = FastOcc(cfg).eval().attention
    with torch.no_grad():  # non-trivial offsets and weights
        att.offsets.weight.normal_(0, 0.5)
        att.weights.weight.normal_(0, 0.5)
    inputs = synthetic_inputs(1, cfg.input_hw, seed=3)
    h, w = cfg.feat_hw
    feat = torch.randn(6, cfg.neck_channels, h, w)
    out = att(feat, inputs)
    xy, vis = project_points_to_feature(voxel_centres(cfg.coarse_grid).reshape(-1, 3), inputs.K,
                                        inputs.T_keyego_from_cam, inputs.img_aug, inputs.bev_aug, cfg.input_hw, 16)
    ref = ((xy[0] + 0.5) / torch.tensor([w, h]) * 2 - 1).clamp(-2, 2)  # (N, Q, 2)
    q = att.queries()
    Q, C = q.shape
    H, P = att.heads, att.points
    loc = ref[:, :, None, None] + att.offsets(q).view(Q, H, P, 2) * torch.tensor([2 / w, 2 / h])
    value = att.value(feat).reshape(6 * H, C // H, h, w)
    sampled = F.grid_sample(value, loc.permute(0, 2, 1, 3, 4).reshape(6 * H, Q, P, 2), align_corners=False)
    weights = att.weights(q).view(Q, H, P).softmax(-1).permute(1, 0, 2)  # (H, Q, P)
    per_cam = (sampled.view(6, H, C // H, Q, P) * weights[None, :, None]).sum(-1).reshape(6, C, Q)
    mean = (per_cam * vis[0][:, None].float()).sum(0) / vis[0].sum(0).clamp_min(1)  # (C, Q)
    x = att.norm1(q + att.out(mean.T))
    x = att.norm2(x + att.ffn(x))
    torch.testing.assert_close(out[0], x.T.reshape(C, 100, 100, 8), atol=1e-4, rtol=1e-4)
