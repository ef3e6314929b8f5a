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


class _FillingDisk:
    """A file whose disk fills up after `room` bytes: writes beyond it raise ENOSPC, as a full disk does."""

    def __init__(self, f, room: int) -> None:  # noqa: ANN001
        self.f, self.room = f, room

    def write(self, data: bytes) -> int:
        import errno

        if len(data) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.f.write(data)

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self.f, name)


def test_full_disk_inside_torch_save_is_an_os_error_and_keeps_the_old_file(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The real torch.save into a file that runs out of space: torch raises a RuntimeError from its zip writer;
    save_checkpoint gives the OSError (ENOSPC) back, the previous file is intact, no temporary is left."""
    import contextlib
    import errno

    import fastocc.checkpoint as ckmod

    cfg = preset("nano")
    path = save_checkpoint(tmp_path / "last.pt", cfg, {"w": torch.ones(2)})
    real_open = ckmod.atomic_open

    @contextlib.contextmanager
    def filling(p):  # noqa: ANN001, ANN202
        with real_open(p) as f:
            yield _FillingDisk(f, room=3000)

    monkeypatch.setattr(ckmod, "atomic_open", filling)
    with pytest.raises(OSError) as info:
        save_checkpoint(path, cfg, {"w": torch.zeros(100_000)})
    assert info.value.errno == errno.ENOSPC and not isinstance(info.value, RuntimeError)
    monkeypatch.undo()
    assert torch.equal(load_checkpoint(path).model["w"], torch.ones(2))
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_other_runtime_errors_of_torch_save_pass_through(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fastocc.checkpoint as ckmod

    def broken(*a, **k):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("not a disk problem")

    monkeypatch.setattr(ckmod.torch, "save", broken)
    with pytest.raises(RuntimeError, match="not a disk problem"):
        save_checkpoint(tmp_path / "x.pt", preset("nano"), {"w": torch.ones(2)})
