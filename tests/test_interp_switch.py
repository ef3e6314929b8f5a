"""The components-ablation switch `ModelConfig.interp_features`: off, the FastOcc head's voxel logits come
from the upsampled BEV map alone (no path from the image features through the sampler); the default is
unchanged; checkpoints, `fastocc train` and the ONNX export carry it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from fastocc.checkpoint import load_checkpoint, load_model, model_config_to_dict, save_checkpoint
from fastocc.model import PRESETS, FastOcc, ModelConfig, preset, synthetic_inputs
from fastocc.model.heads import FastOccHead
from fastocc.train.config import ConfigError, TrainConfig, incompatible_fields, load_config


def _head_inputs(cfg: ModelConfig, seed: int, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    h, w = cfg.feat_hw
    feat = torch.randn(cfg.num_cams, cfg.neck_channels, h, w, generator=g, dtype=dtype)
    bev = torch.randn(1, cfg.context_channels * 8, 100, 100, generator=g, dtype=dtype)
    return feat, bev


def test_default_keeps_interpolated_features() -> None:
    assert ModelConfig().interp_features and all(c.interp_features for c in PRESETS.values())
    assert TrainConfig().interp_features and TrainConfig().model_config().interp_features
    head = FastOccHead(preset("nano"))
    assert head.fuse_img is not None and head.sampler is not None


def test_switch_off_output_ignores_the_image_features() -> None:
    """In float64: the head's classifier runs on (B, X, Y, 1, C_f), the reference's on (B, X, Y, C_f)."""
    torch.manual_seed(0)
    cfg = preset("nano", interp_features=False)
    head = FastOccHead(cfg).eval().double()
    inputs = synthetic_inputs(1, cfg.input_hw)
    feat_a, bev = _head_inputs(cfg, 1, torch.float64)
    feat_b, _ = _head_inputs(cfg, 2, torch.float64)
    assert head.fuse_img is None and head.sampler is None
    with torch.no_grad():
        logits_a, bev_map = head(feat_a, bev, inputs)
        logits_b, _ = head(feat_b, bev, inputs)
        logits_0, _ = head(torch.zeros_like(feat_a), bev, inputs)
        # independent reference: upsample W_B B + b, ReLU, classifier per voxel, same for every z level
        up = F.interpolate(head.fuse_bev(bev_map), size=(200, 200), mode="bilinear", align_corners=False)
        ref = head.classifier(F.relu(up.permute(0, 2, 3, 1)))  # (1, 200, 200, 18)
    assert logits_a.shape == (1, 18, 200, 200, 16)
    assert torch.equal(logits_a, logits_b) and torch.equal(logits_a, logits_0)
    for k in (0, 7, 15):
        torch.testing.assert_close(logits_a[..., k], ref.permute(0, 3, 1, 2), atol=1e-5, rtol=1e-5)


def test_switch_on_output_depends_on_the_image_features() -> None:
    """Control for the test above: with the default head, other image features give other logits."""
    torch.manual_seed(0)
    cfg = preset("nano")
    head = FastOccHead(cfg).eval()
    inputs = synthetic_inputs(1, cfg.input_hw)
    feat_a, bev = _head_inputs(cfg, 1)
    feat_b, _ = _head_inputs(cfg, 2)
    with torch.no_grad():
        diff = (head(feat_a, bev, inputs)[0] - head(feat_b, bev, inputs)[0]).abs().max()
    assert float(diff) > 1e-3


def test_switch_off_network_trains_every_parameter() -> None:
    """No unused parameters (DDP needs none): the image backbone still learns through the view transform."""
    torch.manual_seed(0)
    cfg = preset("nano", interp_features=False)
    net = FastOcc(cfg).train()
    out = net(synthetic_inputs(1, cfg.input_hw))
    (out.voxel_logits.square().mean() + out.depth_probs.mean() + out.bev_logits.mean()).backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None and not n.startswith("backbone.fc.")]
    assert not missing
    assert float(net.backbone.conv1.weight.grad.abs().sum()) > 0


def test_checkpoint_carries_the_switch(tmp_path: Path) -> None:
    torch.manual_seed(0)
    cfg = preset("nano", interp_features=False)
    path = save_checkpoint(tmp_path / "off.pt", cfg, FastOcc(cfg).state_dict())
    model, ckpt = load_model(path)
    assert ckpt.model_config.interp_features is False and model.head.fuse_img is None
    assert not any(k.startswith("head.fuse_img") for k in ckpt.model)


def test_checkpoint_without_the_field_loads_with_the_default(tmp_path: Path) -> None:
    """A checkpoint written before the field existed: its model config JSON has no `interp_features`."""
    torch.manual_seed(0)
    cfg = preset("nano")
    path = save_checkpoint(tmp_path / "old.pt", cfg, FastOcc(cfg).state_dict())
    payload = torch.load(path, weights_only=True)
    old = model_config_to_dict(cfg)
    del old["interp_features"]
    payload["model_config"] = json.dumps(old)
    torch.save(payload, path)
    model, ckpt = load_model(path)
    assert ckpt.model_config.interp_features is True and model.head.fuse_img is not None
    assert load_checkpoint(path).model_config == cfg


def test_train_config_toml_cli_and_resume(tmp_path: Path) -> None:
    toml = tmp_path / "c.toml"
    toml.write_text("[train]\ninterp_features = false\nw_bev = 0.0\n")
    cfg = load_config(toml)
    assert cfg.model_config().interp_features is False and cfg.loss.bev == 0.0
    assert load_config(toml, {"interp_features": True}).model_config().interp_features is True  # CLI wins
    with pytest.raises(ConfigError, match="interp_features"):
        TrainConfig(head="3dfcn", interp_features=False)
    # a run folder written before the new fields existed resumes: missing keys count as their defaults
    saved = TrainConfig().to_dict()
    del saved["interp_features"], saved["scene_sequential"]
    assert incompatible_fields(saved, TrainConfig()) == []
    assert incompatible_fields(saved, TrainConfig(interp_features=False)) == ["interp_features"]


def test_cli_option_reaches_the_config(monkeypatch: pytest.MonkeyPatch) -> None:
    from click.testing import CliRunner

    import fastocc.train as train_pkg
    from cli.fastocc_cli import main

    seen: list[TrainConfig] = []

    def fake_train(cfg: TrainConfig, resume: bool, progress: bool):  # noqa: ANN202
        seen.append(cfg)
        raise SystemExit(0)

    monkeypatch.setattr(train_pkg, "train", fake_train)
    res = CliRunner().invoke(main, ["train", "--no-interp-features", "--out", "x"])
    assert res.exit_code == 0, res.output
    assert seen and seen[0].interp_features is False


def test_export_honours_the_switch(tmp_path: Path) -> None:
    """The fixed-rig ONNX graph of a head without interpolated features matches PyTorch (parity check)."""
    pytest.importorskip("onnxruntime")
    from fastocc.deploy import ExportConfig, export_onnx

    torch.manual_seed(0)
    cfg = preset("nano", interp_features=False)
    ckpt = save_checkpoint(tmp_path / "c.pt", cfg, FastOcc(cfg).state_dict())
    rep = export_onnx(ExportConfig(checkpoint=ckpt, out=tmp_path / "m.onnx", frames=1))
    assert rep.parity.passed and rep.parity.max_abs_diff <= 1e-3 and rep.parity.min_agreement >= 0.999


# -- the second BEV-only value: channels unfolded into the height bins (the paper's reading) ---------------
def test_unfold_gives_every_height_its_own_feature_from_the_bev_map_alone() -> None:
    """In float64: the head classifies all 16 height bins in one batch, the reference one bin at a time."""
    torch.manual_seed(0)
    cfg = preset("nano", interp_features=False, bev_height="unfold")
    head = FastOccHead(cfg).eval().double()
    inputs = synthetic_inputs(1, cfg.input_hw)
    feat_a, bev = _head_inputs(cfg, 1, torch.float64)
    feat_b, _ = _head_inputs(cfg, 2, torch.float64)
    assert head.fuse_img is None and head.sampler is None
    assert head.fuse_bev.out_channels == cfg.fuse_channels * 16
    with torch.no_grad():
        logits, bev_map = head(feat_a, bev, inputs)
        assert torch.equal(logits, head(feat_b, bev, inputs)[0])  # no path from the image features
        up = F.interpolate(head.fuse_bev(bev_map), size=(200, 200), mode="bilinear", align_corners=False)
        cf = cfg.fuse_channels
        for k in (0, 5, 15):  # independent reference: height bin k = channels [k C_f, (k + 1) C_f)
            ref = head.classifier(F.relu(up[:, k * cf:(k + 1) * cf].permute(0, 2, 3, 1)))  # (1, 200, 200, 18)
            torch.testing.assert_close(logits[..., k], ref.permute(0, 3, 1, 2), atol=1e-5, rtol=1e-5)
    assert float((logits[..., 0] - logits[..., 15]).abs().max()) > 1e-3  # varies with height (repeat cannot)


def test_unfold_is_validated_carried_by_checkpoints_and_selected_by_train_config(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="bev_height"):
        preset("nano", bev_height="unfold")  # interpolated features on: the switch does not apply
    with pytest.raises(ValueError, match="bev_height"):
        preset("nano", bev_height="sideways")
    with pytest.raises(ConfigError, match="bev_height"):
        TrainConfig(bev_height="unfold")
    cfg = TrainConfig(interp_features=False, bev_height="unfold").model_config()
    assert cfg.bev_height.value == "unfold"
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / "u.pt", cfg, FastOcc(cfg).state_dict())
    model, ckpt = load_model(path)
    assert ckpt.model_config == cfg and model.head.height_bins == 16
    payload = torch.load(path, weights_only=True)  # written before the field existed: "repeat"
    old = model_config_to_dict(preset("nano", interp_features=False))
    del old["bev_height"]
    payload["model_config"] = json.dumps(old)
    payload["model"] = FastOcc(preset("nano", interp_features=False)).state_dict()
    torch.save(payload, path)
    assert load_model(path)[1].model_config.bev_height.value == "repeat"


def test_cli_bev_height_and_temporal_fusion_reach_the_config(monkeypatch: pytest.MonkeyPatch) -> None:
    from click.testing import CliRunner

    import fastocc.train as train_pkg
    from cli.fastocc_cli import main

    seen: list[TrainConfig] = []

    def fake_train(cfg: TrainConfig, resume: bool, progress: bool):  # noqa: ANN202
        seen.append(cfg)
        raise SystemExit(0)

    monkeypatch.setattr(train_pkg, "train", fake_train)
    res = CliRunner().invoke(main, ["train", "--no-interp-features", "--bev-height", "unfold", "--temporal-fusion",
                                    "cached", "--out", "x"])
    assert res.exit_code == 0, res.output
    assert (seen[0].bev_height, seen[0].temporal_fusion) == ("unfold", "cached")


def test_export_honours_unfold(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    from fastocc.deploy import ExportConfig, export_onnx

    torch.manual_seed(0)
    cfg = preset("nano", interp_features=False, bev_height="unfold")
    ckpt = save_checkpoint(tmp_path / "c.pt", cfg, FastOcc(cfg).state_dict())
    rep = export_onnx(ExportConfig(checkpoint=ckpt, out=tmp_path / "m.onnx", frames=1))
    assert rep.parity.passed and rep.parity.max_abs_diff <= 1e-3 and rep.parity.min_agreement >= 0.999
