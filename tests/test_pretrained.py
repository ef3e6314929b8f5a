"""Backbone weights under each source's key names: torchvision (bare), mmdet (`state_dict` / `backbone.`),
mmdet3d (`img_backbone.`), FCOS3D's DCN ResNet (`conv2.conv_offset.*`), and the one-line errors."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from fastocc.model.pretrained import (
    abbreviate,
    backbone_state,
    is_caffe_style,
    load_backbone,
    match_backbone,
    read_weights,
)
from fastocc.model.resnet import ResNet, resnet
from occdata.errors import OccDataError, OccDataWarning
from occdata.sensors.image_ops import IMAGENET_MEAN, IMAGENET_STD


def _small(depth: int = 50) -> ResNet:
    """A narrow ResNet in the real layout (bottlenecks, downsample branches), cheap to build."""
    return resnet(depth, base_width=8)


def _random_state(net: ResNet, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {k: (torch.randn(v.shape, generator=g) if v.is_floating_point() else v.clone())
            for k, v in net.state_dict().items()}


def _mmdet(state: dict[str, torch.Tensor], prefix: str) -> dict:
    """An mmdet/mmdet3d checkpoint: meta, `state_dict` with the ResNet under `prefix` (no `fc`), a neck and head."""
    sd = {prefix + k: v for k, v in state.items() if not k.startswith("fc.")}
    sd[prefix.replace("backbone", "neck") + "lateral_convs.0.conv.weight"] = torch.ones(4, 4, 1, 1)
    sd["bbox_head.cls_convs.0.conv.weight"] = torch.ones(4, 4, 3, 3)
    return {"meta": {"mmdet_version": "2.x", "CLASSES": ("car", "truck"), "epoch": 12}, "state_dict": sd}


def _assert_loaded(net: ResNet, state: dict[str, torch.Tensor]) -> None:
    got = net.state_dict()
    for key, value in state.items():
        if not key.startswith("fc.") and not key.endswith("num_batches_tracked"):
            assert torch.equal(got[key], value), key


def test_torchvision_state_dict_loads_as_is(tmp_path: Path) -> None:
    state = _random_state(_small(), 1)
    torch.save(state, tmp_path / "resnet50-0676ba61.pth")
    net = _small()
    line = load_backbone(net, tmp_path / "resnet50-0676ba61.pth")
    _assert_loaded(net, state)
    assert torch.equal(net.fc.weight, state["fc.weight"])  # the classifier rides along when present
    assert line == f"backbone: {len(state)} tensors from resnet50-0676ba61.pth (keys under 'no prefix')"


def test_old_torchvision_file_without_batch_counters_loads(tmp_path: Path) -> None:
    """resnet50-19c8e357.pth predates BatchNorm's num_batches_tracked."""
    state = {k: v for k, v in _random_state(_small(), 2).items() if not k.endswith("num_batches_tracked")}
    torch.save(state, tmp_path / "old.pth")
    net = _small()
    load_backbone(net, tmp_path / "old.pth")
    _assert_loaded(net, state)


@pytest.mark.parametrize("prefix", ["backbone.", "img_backbone.", "module.img_backbone."])
def test_mmdet_checkpoint_loads_backbone_only(tmp_path: Path, prefix: str) -> None:
    state = _random_state(_small(), 3)
    torch.save(_mmdet(state, prefix), tmp_path / "ckpt.pth")
    net = _small()
    fc_before = net.fc.weight.clone()
    line = load_backbone(net, tmp_path / "ckpt.pth")
    _assert_loaded(net, state)
    assert torch.equal(net.fc.weight, fc_before)  # mmdet has no classifier: ours stays as it was
    n_resnet = sum(1 for k in state if not k.startswith("fc."))
    assert line == f"backbone: {n_resnet} tensors from ckpt.pth (keys under {prefix!r})"


def test_fcos3d_dcn_offsets_are_reported_and_skipped(tmp_path: Path) -> None:
    """FCOS3D's ResNet-101 has DCNv2 in stages 3 and 4: `conv2.weight` is a 3x3 kernel (loads) and
    `conv2.conv_offset.{weight,bias}` (27 = 3 x 3 x 3 offset/mask channels) has no counterpart."""
    net = _small(101)
    state = _random_state(net, 4)
    ckpt = _mmdet(state, "img_backbone.")
    dcn_blocks = [k[: -len(".conv2.weight")] for k in state if k.startswith(("layer3.", "layer4."))
                  and k.endswith(".conv2.weight")]
    assert len(dcn_blocks) == 23 + 3
    for block in dcn_blocks:
        planes = state[f"{block}.conv2.weight"].shape[1]
        ckpt["state_dict"][f"img_backbone.{block}.conv2.conv_offset.weight"] = torch.zeros(27, planes, 3, 3)
        ckpt["state_dict"][f"img_backbone.{block}.conv2.conv_offset.bias"] = torch.zeros(27)
    torch.save(ckpt, tmp_path / "fcos3d.pth")
    with pytest.warns(OccDataWarning, match=r"52 deformable-conv offset tensors .* layer3\.0\.conv2\.conv_offset"):
        load_backbone(net, tmp_path / "fcos3d.pth")
    _assert_loaded(net, state)


def test_missing_and_extra_keys_are_one_line_and_nothing_loads(tmp_path: Path) -> None:
    state = _random_state(_small(), 5)
    ckpt = _mmdet(state, "backbone.")
    del ckpt["state_dict"]["backbone.layer2.0.bn1.running_var"]
    ckpt["backbone.layer2.0.bn1.running_var"] = "not here: in state_dict"  # noise outside the container
    ckpt["state_dict"]["backbone.layer5.0.conv1.weight"] = torch.zeros(1)
    torch.save(ckpt, tmp_path / "bad.pth")
    net = _small()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    with pytest.raises(OccDataError) as err:
        load_backbone(net, tmp_path / "bad.pth")
    msg = str(err.value)
    assert "\n" not in msg
    assert "missing 1: layer2.0.bn1.running_var" in msg and "extra 1: layer5.0.conv1.weight" in msg
    assert "'backbone.'" in msg
    assert all(torch.equal(net.state_dict()[k], v) for k, v in before.items())


def test_wrong_depth_names_the_shapes(tmp_path: Path) -> None:
    """ResNet-50 weights into a ResNet-18: bottleneck keys are extra, the shared ones have other shapes."""
    torch.save(_random_state(_small(50), 6), tmp_path / "r50.pth")
    with pytest.raises(OccDataError, match=r"extra \d+: .*; wrong shape \d+: layer1\.0\.conv1\.weight"):
        load_backbone(_small(18), tmp_path / "r50.pth")


def test_deep_stem_is_named(tmp_path: Path) -> None:
    state = {k: v for k, v in _random_state(_small(), 7).items() if not k.startswith(("conv1.", "bn1."))}
    state |= {"stem.0.weight": torch.zeros(16, 3, 3, 3), "stem.1.weight": torch.zeros(16)}
    torch.save({"state_dict": {"backbone." + k: v for k, v in state.items()}}, tmp_path / "v1d.pth")
    with pytest.raises(OccDataError, match=r"missing \d+: conv1.weight, bn1.*deep-stem"):
        load_backbone(_small(), tmp_path / "v1d.pth")


def test_abbreviate_counts_and_cuts() -> None:
    assert abbreviate(["a", "b"]) == "2: a, b"
    assert abbreviate([f"k{i}" for i in range(40)]) == "40: k0, k1, k2, k3, ..."


def test_prefix_search_refuses_none_and_two() -> None:
    state = _random_state(_small(18), 8)
    with pytest.raises(OccDataError, match="no ResNet keys"):
        backbone_state({"neck.conv.weight": torch.zeros(1)})
    two = {"a." + k: v for k, v in state.items()} | {"b." + k: v for k, v in state.items()}
    with pytest.raises(OccDataError, match="several ResNets"):
        backbone_state(two)
    with pytest.raises(OccDataError, match="no ResNet keys"):  # a prefix ends with a dot
        backbone_state({"x_layer1.0.conv1.weight": torch.zeros(1)})
    assert backbone_state({"m.layer1.0.conv1.weight": torch.ones(1), "n.x": torch.ones(1)})[0] == "m."


def test_match_keeps_sources_apart() -> None:
    ours = {"a": torch.zeros(2), "fc.weight": torch.zeros(1), "bn.num_batches_tracked": torch.zeros(())}
    m = match_backbone(ours, {"a": torch.ones(3), "b.conv_offset.weight": torch.ones(1), "c": torch.ones(1)})
    assert m.missing == () and m.extra == ("c",) and m.dcn_offsets == ("b.conv_offset.weight",)
    assert m.mismatched == ("a ((3,) vs (2,))",) and m.loaded == {}


def test_unsafe_or_foreign_files_are_one_line(tmp_path: Path) -> None:
    torch.save({"state_dict": {}, "meta": {"hook": warnings.WarningMessage}}, tmp_path / "pickled.pth")
    with pytest.raises(OccDataError, match=r"not readable with weights_only=True \(Unsupported global: .*Warning"):
        read_weights(tmp_path / "pickled.pth")
    (tmp_path / "text.pth").write_text("hello")
    with pytest.raises(OccDataError, match="not a torch weights file"):
        read_weights(tmp_path / "text.pth")
    torch.save([1, 2], tmp_path / "list.pth")
    with pytest.raises(OccDataError, match="holds no state dict of tensors"):
        read_weights(tmp_path / "list.pth")


def test_caffe_style_stem_is_converted_exactly(tmp_path: Path) -> None:
    """FCOS3D's ResNet (mmdet `style='caffe'`) saw BGR pixels minus the mean (std 1); ours sees RGB
    (pixels - mean) / std. After loading, our conv1 on our input equals the checkpoint's conv1 on its own
    input, computed here from the raw pixels."""
    net = _small()
    state = _random_state(net, 9)
    ckpt = _mmdet(state, "backbone.")
    ckpt["meta"]["config"] = "model = dict(backbone=dict(type='ResNet', depth=101, style='caffe'))"
    torch.save(ckpt, tmp_path / "caffe.pth")
    line = load_backbone(net, tmp_path / "caffe.pth")
    assert "caffe-style: conv1 converted" in line
    pixels = torch.rand(1, 3, 40, 56, generator=torch.Generator().manual_seed(0)) * 255  # RGB 0..255
    mean, std = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    x_ours = (pixels - mean) / std
    x_caffe = (pixels - mean).flip(1)  # BGR, minus the mean, unit std
    w_caffe = state["conv1.weight"]
    expected = F.conv2d(x_caffe, w_caffe, stride=2, padding=3)
    got = net.conv1(x_ours)
    assert torch.allclose(got, expected, rtol=1e-4, atol=1e-3 * expected.abs().max().item())
    _assert_loaded(net, {k: v for k, v in state.items() if k != "conv1.weight"})


def test_pytorch_style_checkpoint_is_not_converted(tmp_path: Path) -> None:
    state = _random_state(_small(), 10)
    ckpt = _mmdet(state, "backbone.")
    ckpt["meta"]["config"] = "backbone=dict(type='ResNet', style='pytorch')"
    torch.save(ckpt, tmp_path / "pt.pth")
    net = _small()
    assert "caffe" not in load_backbone(net, tmp_path / "pt.pth")
    assert torch.equal(net.conv1.weight, state["conv1.weight"])
    assert is_caffe_style('style = "caffe"') and not is_caffe_style("style='pytorch'  # not caffe")
    assert read_weights(tmp_path / "pt.pth")[1] == ckpt["meta"]["config"]
