"""Issue 12 item 6: a missing chunk of a committed sample is corruption for every reader of the store.

zarr reads an absent chunk as its fill value without a word; these tests delete chunk files (or
drop an inner chunk from a shard) and check that the loader, dump, check-projection, show-batch,
info and verify all refuse with a line naming the sample, while legitimately absent chunks
(unlabelled samples, visibility never computed) stay fine.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.errors import OccDataError
from occdata.store.integrity import CorruptStoreError
from occdata.store.layout import FLAT_ARRAYS, PER_SAMPLE
from occdata.store.pack import drop_pack
from occdata.store.reader import open_store


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


@pytest.fixture
def store(synth_store: Path, tmp_path: Path) -> Path:
    out = tmp_path / "s.zarr"
    shutil.copytree(synth_store, out)
    return out


def _chunk_files(store: Path, name: str) -> list[Path]:
    return sorted(p for p in (store / name / "c").rglob("*") if p.is_file())


def _load_all(store: Path) -> list[int]:
    from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader

    cfg = SampleConfig(image=ImageAugConfig(height=96, width=160, train=False), bev=BevAugConfig(train=False))
    loader = make_loader(LoaderConfig(store=store, batch_size=2, sample=cfg), num_workers=0)
    return [i for b in loader for i in b.sample_index.tolist()]


def _one_error_line(text: str) -> str:
    assert "Traceback" not in text, text
    lines = [ln for ln in text.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1, text
    return lines[0]


def test_deleted_label_shard_is_corruption_everywhere(store: Path, tmp_path: Path) -> None:
    """The issue's example: loader yielded has_labels=True with 100% ignore labels, dump wrote K=0."""
    (shard,) = _chunk_files(store, "labels/semantics")
    shard.unlink()
    with pytest.raises(CorruptStoreError, match=r"sample \d+ \(\w+\).*labels/semantics"):
        _load_all(store)
    code, text = _cli("dump", "--store", str(store), "-i", "1", "--out", str(tmp_path / "d.npz"))
    assert code == 1 and "labels/semantics" in _one_error_line(text) and "sample 1" in text
    assert not (tmp_path / "d.npz").exists()
    code, text = _cli("verify", "--store", str(store), "--no-progress")
    assert code == 1
    bad = [ln for ln in text.splitlines() if ln.startswith("CORRUPT sample")]
    assert len({ln.split()[2] for ln in bad if "labels/semantics" in ln}) == 6, text  # every labelled sample


def test_deleted_state_chunk_is_reported(store: Path, tmp_path: Path) -> None:
    """Was: every sample read as pending, `verify` said "all verified" and exit 0."""
    (chunk,) = _chunk_files(store, "status/state")
    chunk.unlink()
    for args in (("verify", "--no-progress"), ("info",), ("dump", "-i", "0", "--out", str(tmp_path / "x.npz")),
                 ("check-projection", "-i", "0", "--out", str(tmp_path / "x.png"))):
        code, text = _cli(args[0], "--store", str(store), *args[1:])
        assert code == 1, (args, text)
        assert "samples 0..5" in _one_error_line(text) and "missing" in text
    # The loader reads the copies the build's final commit packed (occdata.store.pack): they still hold
    # the committed flags. Without them it reads the chunks and refuses.
    assert sorted(_load_all(store)) == list(range(6))
    drop_pack(zarr.open_group(str(store), mode="r+"))
    with pytest.raises(CorruptStoreError, match="commit flags"):
        _load_all(store)


_PRESENT = [s.name for s in PER_SAMPLE if not s.name.startswith("visibility/") and s.name != "status/state"]


@pytest.mark.parametrize("name", _PRESENT + list(FLAT_ARRAYS))
def test_every_array_missing_chunk_found_by_verify(store: Path, name: str) -> None:
    files = _chunk_files(store, name)
    assert files, f"{name} has no chunk in the test store"
    files[0].unlink()
    code, text = _cli("verify", "--store", str(store), "--no-progress")
    assert code == 1, text
    bad = [ln for ln in text.splitlines() if ln.startswith("CORRUPT sample") and name in ln]
    # Named as a missing chunk (checked by listing), not only as a checksum mismatch (which the old
    # verify also found for most arrays, but not for status/checksum or a fill-valued chunk).
    assert any(f"chunk {name}/c/" in ln and "is missing" in ln for ln in bad), text


@pytest.mark.parametrize("name", ["labels/present", "calib/K", "images/offsets", "depth/offsets",
                                  "images/jpeg", "depth/uvd", "labels/bev", "labels/mask_camera"])
def test_loader_refuses_missing_chunk(store: Path, name: str) -> None:
    _chunk_files(store, name)[0].unlink()
    drop_pack(zarr.open_group(str(store), mode="r+"))  # small arrays: from their chunks, not the packed copies
    with pytest.raises(CorruptStoreError, match=rf"sample \d+ .*{name}"):
        _load_all(store)


def test_missing_inner_chunk_of_present_shard(store: Path) -> None:
    """A shard whose index lost one sample's inner chunk: that sample reads as fill (255)."""
    g = zarr.open_group(str(store), mode="r+")
    g["labels/semantics"][2] = 255  # equal to the fill value: zarr drops the inner chunk from the shard
    assert len(_chunk_files(store, "labels/semantics")) == 1  # the shard file itself is still there
    with pytest.raises(CorruptStoreError, match=r"sample 2 .*labels/semantics.*checksum"):
        _load_all(store)
    with pytest.raises(CorruptStoreError, match="sample 2"):
        open_store(store).sample_arrays(2, ("labels/semantics",))
    code, text = _cli("verify", "--store", str(store), "--no-progress")
    assert code == 1 and "CORRUPT sample 2" in text


def test_legitimately_absent_chunks_are_fine(synth_root: Path, tmp_path: Path) -> None:
    """No labels at all: every label chunk and the labels/present chunk are absent, and that is right."""
    from occdata.store.build import BuildConfig, build_store

    out = tmp_path / "nolabels.zarr"
    build_store(BuildConfig(root=synth_root, out=out, progress=False))
    assert not _chunk_files(out, "labels/semantics") and not _chunk_files(out, "labels/present")
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text
    assert sorted(_load_all(out)) == list(range(6))
    code, text = _cli("dump", "--store", str(out), "-i", "0", "--out", str(tmp_path / "d.npz"))
    assert code == 0, text


def test_verify_reports_pending_samples(store: Path) -> None:
    g = zarr.open_group(str(store), mode="r+")
    g["status/state"][3:] = 0
    g.attrs["complete"] = False
    code, text = _cli("verify", "--store", str(store), "--no-progress")
    assert code == 1 and "PENDING 3 of 6" in text and "--resume" in text, text
    assert "CORRUPT" not in text


def test_dump_and_check_projection_on_failed_or_pending_sample(store: Path, tmp_path: Path) -> None:
    g = zarr.open_group(str(store), mode="r+")
    g["status/state"][5] = 0
    g["status/state"][4] = 2
    g.attrs["errors"] = [{"index": 4, "token": "t", "reason": "corrupt JPEG x.jpg"}]
    g.attrs["complete"] = False
    for cmd, suffix in (("dump", "npz"), ("check-projection", "png")):
        code, text = _cli(cmd, "--store", str(store), "-i", "4", "--out", str(tmp_path / f"a.{suffix}"))
        assert code == 1 and "failed to build: corrupt JPEG x.jpg" in _one_error_line(text)
        code, text = _cli(cmd, "--store", str(store), "-i", "5", "--out", str(tmp_path / f"a.{suffix}"))
        assert code == 1 and "pending" in _one_error_line(text)


def test_reader_api_raises_occdata_error_subclass(store: Path) -> None:
    (shard,) = _chunk_files(store, "labels/bev")
    shard.unlink()
    with pytest.raises(OccDataError):
        open_store(store).sample_arrays(0)
    np.testing.assert_equal(open_store(store).sample_arrays(0, ("calib/K",))["calib/K"].shape, (6, 3, 3))


def test_bev_gt_does_not_recompute_from_a_missing_shard(store: Path) -> None:
    """bev-gt used to rebuild the BEV GT from all-255 semantics and re-checksum it: corruption laundered."""
    (shard,) = _chunk_files(store, "labels/semantics")
    shard.unlink()
    code, text = _cli("bev-gt", "--store", str(store), "--no-progress")
    assert code == 1 and "labels/semantics" in _one_error_line(text) and "sample 0" in text
