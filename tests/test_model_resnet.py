"""ResNet parameter names/shapes match torchvision's layout; torchvision-style state dict files load as-is."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fastocc.model import FastOcc, preset
from fastocc.model.resnet import resnet
from occdata.errors import OccDataError

# torchvision's published parameter counts (fc included)
TORCHVISION_PARAMS = {18: 11_689_512, 50: 25_557_032, 101: 44_549_160}


@pytest.mark.parametrize("depth", [18, 50, 101])
def test_parameter_count_matches_torchvision(depth: int) -> None:
    with torch.device("meta"):
        net = resnet(depth)
    assert sum(p.numel() for p in net.parameters()) == TORCHVISION_PARAMS[depth]


def test_resnet50_key_names_and_shapes_follow_torchvision_layout() -> None:
    with torch.device("meta"):
        sd = resnet(50).state_dict()
    expected = {
        "conv1.weight": (64, 3, 7, 7),
        "bn1.running_mean": (64,),
        "layer1.0.conv1.weight": (64, 64, 1, 1),
        "layer1.0.conv2.weight": (64, 64, 3, 3),
        "layer1.0.conv3.weight": (256, 64, 1, 1),
        "layer1.0.downsample.0.weight": (256, 64, 1, 1),
        "layer1.0.downsample.1.weight": (256,),
        "layer2.0.conv2.weight": (128, 128, 3, 3),
        "layer2.0.downsample.0.weight": (512, 256, 1, 1),
        "layer3.5.bn3.num_batches_tracked": (),
        "layer4.2.conv3.weight": (2048, 512, 1, 1),
        "fc.weight": (1000, 2048),
        "fc.bias": (1000,),
    }
    for key, shape in expected.items():
        assert tuple(sd[key].shape) == shape, key
    # 53 convs + 53 BNs x (weight, bias, running_mean, running_var, num_batches_tracked) + fc (2) = 320
    assert len(sd) == 320
    assert not any(k.startswith("layer5") or "layer1.3" in k for k in sd)


def test_pretrained_state_dict_file_loads_without_renaming(tmp_path: Path) -> None:
    cfg = preset("nano")
    src = resnet(cfg.backbone.depth, cfg.backbone.base_width)
    for p in src.parameters():
        torch.nn.init.normal_(p)
    path = tmp_path / "resnet18-test.pth"
    torch.save(src.state_dict(), path)
    net = FastOcc(cfg)
    net.load_pretrained_backbone(path)
    for key, value in src.state_dict().items():
        assert torch.equal(net.backbone.state_dict()[key], value), key
    # mmdet's prefix loads too; a planted extra key is one error line (key mapping: tests/test_pretrained.py)
    bad = {("backbone." + k): v for k, v in src.state_dict().items()} | {"backbone.layer9.0.conv1.weight": value}
    torch.save(bad, path)
    with pytest.raises(OccDataError, match="extra 1: layer9.0.conv1.weight"):
        net.load_pretrained_backbone(path)
