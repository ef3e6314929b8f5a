"""Issue 12 item 7: options that used to be accepted silently and do the wrong thing."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from fastocc.data import LoaderConfig, StoreDataset, make_loader
from occdata.errors import OccDataError
from occdata.store.build import BuildConfig, build_store
from occdata.store.sample import SampleOptions


@pytest.mark.parametrize("bs", [0, -1, 2.0, True])
def test_batch_size_must_be_positive_int(synth_store: Path, bs) -> None:
    """batch_size 0 used to turn the whole epoch into one batch."""
    with pytest.raises(OccDataError, match="batch_size must be an integer >= 1"):
        LoaderConfig(store=synth_store, batch_size=bs)


def test_drop_last_with_fewer_samples_than_a_batch_is_an_error(synth_store: Path) -> None:
    """6 samples, batch 8, drop_last: zero batches an epoch, silently. Now refused at construction."""
    with pytest.raises(OccDataError, match="drop_last with 6 samples and batch_size 8 would yield no batch"):
        make_loader(LoaderConfig(store=synth_store, batch_size=8, drop_last=True))
    assert len(StoreDataset(LoaderConfig(store=synth_store, batch_size=8))) == 6  # without drop_last: fine


def test_drop_last_warns_when_a_rank_gets_no_batch(synth_store: Path) -> None:
    """Enough samples overall, but this rank's share is all dropped: a warning (it is not known upfront)."""
    from fastocc.data import BevAugConfig, ImageAugConfig, SampleConfig

    cfg = SampleConfig(image=ImageAugConfig(height=96, width=160, train=False), bev=BevAugConfig(train=False))
    ds = StoreDataset(LoaderConfig(store=synth_store, batch_size=4, drop_last=True, sequential=True, rank=0,
                                   world_size=2, sample=cfg))
    with pytest.warns(RuntimeWarning, match="drop_last: rank 0 worker 0 got 3 samples"):
        assert list(ds) == []


def test_jpeg_quality_out_of_range_is_rejected(synth_root: Path, tmp_path: Path) -> None:
    r = CliRunner().invoke(main, ["build", "--root", str(synth_root), "--out", str(tmp_path / "q.zarr"),
                                  "--image-scale", "0.5", "--jpeg-quality", "500", "--no-progress"])
    assert r.exit_code == 2 and "500 is not in the range 1<=x<=100" in r.output
    with pytest.raises(OccDataError, match="--jpeg-quality must be in"):
        build_store(BuildConfig(root=synth_root, out=tmp_path / "q.zarr", progress=False,
                                options=SampleOptions(image_scale=0.5, jpeg_quality=0)))
    assert not (tmp_path / "q.zarr").exists()
