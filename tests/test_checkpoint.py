"""Checkpoints: config round trip, atomic write, weights_only load, clear errors on other files."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fastocc.checkpoint import (
    CheckpointError,
    load_checkpoint,
    load_model,
    model_config_from_dict,
    model_config_to_dict,
    save_checkpoint,
)
from fastocc.model import PRESETS, FastOcc, HeadKind, preset


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_model_config_round_trip(name: str) -> None:
    cfg = preset(name, head=HeadKind.FCN3D, num_history=2)
    assert model_config_from_dict(model_config_to_dict(cfg)) == cfg


def test_save_load_model(tmp_path: Path) -> None:
    torch.manual_seed(0)
    cfg = preset("nano")
    model = FastOcc(cfg)
    path = save_checkpoint(tmp_path / "a.pt", cfg, model.state_dict(), meta={"epoch": 3}, step=7)
    loaded, ckpt = load_model(path)
    assert ckpt.model_config == cfg and ckpt.meta == {"epoch": 3} and ckpt.payload["step"] == 7
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    assert not loaded.training
    assert [p.name for p in tmp_path.iterdir()] == ["a.pt"]  # no temporary file left


def test_failed_write_keeps_previous(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = preset("nano")
    path = save_checkpoint(tmp_path / "a.pt", cfg, {"w": torch.ones(2)})

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", boom)
    with pytest.raises(OSError):
        save_checkpoint(path, cfg, {"w": torch.zeros(2)})
    monkeypatch.undo()
    assert torch.equal(load_checkpoint(path).model["w"], torch.ones(2))
    assert [p.name for p in tmp_path.iterdir()] == ["a.pt"]


def test_other_files_are_clear_errors(tmp_path: Path) -> None:
    torch.save({"conv1.weight": torch.zeros(1)}, tmp_path / "bare.pth")
    with pytest.raises(CheckpointError, match="bare state dict"):
        load_checkpoint(tmp_path / "bare.pth")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(CheckpointError, match="not a readable"):
        load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(CheckpointError, match="no such"):
        load_checkpoint(tmp_path / "missing.pt")

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    torch.save({"format": "fastocc.checkpoint", "x": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError, match="not a readable"):
        load_checkpoint(tmp_path / "evil.pt")
