"""StoreDataset on a replayed real-keyframe store: sharding, orders, labels, errors, the Batch contract."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr
from replicated_tree import make_replicated_tree

from fastocc.data import Batch, BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, StoreDataset, make_loader
from occdata.errors import OccDataError
from occdata.store.bev import unpack_bev
from occdata.store.build import BuildConfig, build_store, consolidate
from occdata.store.pack import write_pack
from occdata.store.reader import open_store

TEST = SampleConfig(image=ImageAugConfig(train=False), bev=BevAugConfig(train=False))
SMALL = SampleConfig(image=ImageAugConfig(height=128, width=352))  # cheaper decode for plumbing tests


@pytest.fixture(scope="module")
def store(real_nuscenes_root, real_occ3d_label, tmp_path_factory) -> Path:
    """2 scenes x 6 samples (block 4). Scene 1 (val) has no labels; sample 4 is marked as a build error."""
    tree = make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory.mktemp("rep") / "ns", 2, 6)
    shutil.rmtree(tree / "gts" / "replay-0001")
    out = tmp_path_factory.mktemp("store") / "rep.zarr"
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=4, progress=False))
    root = zarr.open_group(str(out), mode="r+")
    root["status/state"][4] = 2
    write_pack(root)  # as a build that recorded the failure commits it (the loader reads the packed copies)
    consolidate(str(out))
    return out


def _indices(loader) -> list[int]:
    return [i for b in loader for i in b.sample_index.tolist()]


@pytest.mark.parametrize("sequential", [False, True])
def test_every_sample_exactly_once_over_2_ranks_x_2_workers(store: Path, sequential: bool) -> None:
    seen: list[int] = []
    per_rank = []
    for rank in range(2):
        cfg = LoaderConfig(store=store, batch_size=2, sequential=sequential, sample=SMALL, seed=7, rank=rank,
                           world_size=2)
        got = _indices(make_loader(cfg, num_workers=2))
        per_rank.append(got)
        seen += got
    assert sorted(seen) == [i for i in range(12) if i != 4]  # the failed sample is never yielded
    assert all(len(r) >= 4 for r in per_rank)


def test_order_is_deterministic_for_seed_and_epoch(store: Path) -> None:
    def run(seed: int, epoch: int) -> tuple[list[int], torch.Tensor]:
        ds = StoreDataset(LoaderConfig(store=store, batch_size=11, sample=SMALL, seed=seed, shuffle_buffer=3))
        ds.set_epoch(epoch)
        (b,) = list(ds)
        return b.sample_index.tolist(), b.img_aug

    a, b, c = run(1, 0), run(1, 0), run(1, 1)
    assert a[0] == b[0] and torch.equal(a[1], b[1])
    assert a[0] != c[0] and sorted(a[0]) == sorted(c[0])
    assert not torch.equal(a[1], c[1])


def test_padding_equalises_ranks(store: Path) -> None:
    counts = []
    for rank in range(3):
        cfg = LoaderConfig(store=store, sample=SMALL, rank=rank, world_size=3, pad=True, batch_size=8)
        counts.append(len(_indices(StoreDataset(cfg))))
    assert len(set(counts)) == 1 and sum(counts) >= 11


def test_batch_contract_and_test_mode(store: Path) -> None:
    cfg = LoaderConfig(store=store, batch_size=3, sequential=True, sample=TEST, seed=1, segment_len=None)
    ds = StoreDataset(cfg)
    batches = list(ds)
    b = batches[0]
    B = len(b)
    shapes = {
        "images": ((B, 6, 3, 256, 704), torch.float32), "K": ((B, 6, 3, 3), torch.float32),
        "T_keyego_from_cam": ((B, 6, 4, 4), torch.float32), "img_aug": ((B, 6, 3, 3), torch.float32),
        "bev_aug": ((B, 4, 4), torch.float32), "T_global_from_keyego": ((B, 4, 4), torch.float32),
        "seq_start": ((B,), torch.bool), "semantics": ((B, 200, 200, 16), torch.int64),
        "mask_camera": ((B, 200, 200, 16), torch.bool), "mask_lidar": ((B, 200, 200, 16), torch.bool),
        "bev_target": ((B, 18, 200, 200), torch.float32), "depth_target": ((B, 6, 16, 44), torch.float32),
        "has_labels": ((B,), torch.bool), "sample_index": ((B,), torch.int64),
        "prev_index": ((B, 16), torch.int64), "prev_valid": ((B, 16), torch.bool),
        "T_cur_from_prev": ((B, 16, 4, 4), torch.float32),
    }
    for name, (shape, dtype) in shapes.items():
        t = getattr(b, name)
        assert tuple(t.shape) == shape and t.dtype == dtype, name
    # Test mode: no randomness at all (another seed gives the same batch).
    other = list(StoreDataset(LoaderConfig(store=store, batch_size=3, sequential=True, sample=TEST, seed=2)))[0]
    assert torch.equal(b.images, other.images) and torch.equal(b.depth_target, other.depth_target)
    assert torch.equal(b.bev_aug, torch.eye(4).expand(B, 4, 4))
    reader = open_store(store)
    for k, i in enumerate(b.sample_index.tolist()):
        a = reader.sample_arrays(i, ("labels/semantics", "labels/bev", "calib/K"))
        if b.has_labels[k]:
            np.testing.assert_array_equal(b.semantics[k].numpy(), a["labels/semantics"])
            np.testing.assert_array_equal(b.bev_target[k].numpy(), unpack_bev(a["labels/bev"]))
        np.testing.assert_allclose(b.K[k].numpy(), a["calib/K"], rtol=1e-6)
        assert (b.depth_target[k] > 0).sum() > 300
    moved = b.to("cpu")
    assert isinstance(moved, Batch) and torch.equal(moved.images, b.images)
    inputs = b.inputs()
    assert inputs.images is b.images and inputs.seq_start is b.seq_start and inputs.bev_aug is b.bev_aug
    if torch.cuda.is_available():
        assert b.pin_memory().images.is_pinned()


def test_label_less_samples_yield_ignore_filled_targets(store: Path) -> None:
    ds = StoreDataset(LoaderConfig(store=store, batch_size=4, sample=SMALL, splits=("val",)))
    batches = list(ds)
    assert sorted(_indices(batches)) == list(range(6, 12))
    for b in batches:
        assert not b.has_labels.any()
        assert (b.semantics == 255).all() and not b.mask_camera.any() and not b.mask_lidar.any()
        assert (b.bev_target == 0).all()
        assert (b.depth_target > 0).any()  # inputs and depth are still there
    labelled = list(StoreDataset(LoaderConfig(store=store, batch_size=8, sample=SMALL, splits=("train",))))
    assert all(b.has_labels.all() for b in labelled)


def test_sequential_order_walks_scenes_in_time(store: Path) -> None:
    ds = StoreDataset(LoaderConfig(store=store, batch_size=2, sequential=True, sample=SMALL, seed=3))
    batches = list(ds)
    lanes: dict[int, list[tuple[int, bool]]] = {}
    for b in batches:
        for slot, (i, start) in enumerate(zip(b.sample_index.tolist(), b.seq_start.tolist(), strict=True)):
            lanes.setdefault(slot, []).append((i, start))
    reader = open_store(store)
    scene = reader.small("sample/scene_index")
    for lane in lanes.values():
        for (i0, _), (i1, s1) in zip(lane, lane[1:], strict=False):
            # Within a segment: the next sample of the same scene; elsewhere a marked start.
            assert s1 or (i1 == i0 + 1 and scene[i1] == scene[i0])
    starts = {i for b in batches for i, s in zip(b.sample_index.tolist(), b.seq_start.tolist(), strict=True) if s}
    assert {0, 5, 6} <= starts  # scene starts and the sample after the failed one
    # Relative poses: the replayed scenes move 4 m per keyframe.
    b = next(b for b in batches if 11 in b.sample_index.tolist())
    k = b.sample_index.tolist().index(11)
    assert b.prev_index[k, :5].tolist() == [10, 9, 8, 7, 6] and b.prev_valid[k].sum() == 5
    assert abs(float(b.T_cur_from_prev[k, 0, :3, 3].norm()) - 4.0) < 1e-4
    c = next(b for b in batches if 5 in b.sample_index.tolist())
    k = c.sample_index.tolist().index(5)
    assert c.prev_index[k, 0] == 4 and not c.prev_valid[k, 0]  # failed previous frame: not usable


def test_fsspec_url(store: Path) -> None:
    ds = StoreDataset(LoaderConfig(store=f"file://{store}", batch_size=16, sample=SMALL))
    assert sorted(_indices(ds)) == [i for i in range(12) if i != 4]


def _corrupt_copy(store: Path, tmp_path: Path) -> tuple[Path, list[str]]:
    bad = tmp_path / "bad.zarr"
    shutil.copytree(store, bad)
    shard = bad / "labels" / "semantics" / "c" / "0" / "0" / "0" / "0"
    data = bytearray(shard.read_bytes())
    for k in range(len(data) // 4, len(data) // 2):
        data[k] ^= 0x5A
    shard.write_bytes(bytes(data))
    reader = open_store(bad)
    failing = []
    for i in range(4):
        try:
            reader.sample_arrays(i, ("labels/semantics",))
        except OccDataError:
            failing.append(reader.token(i))
    assert failing
    return bad, failing


@pytest.mark.timeout(30)
@pytest.mark.parametrize("workers", [0, 2])
def test_corrupt_chunk_names_the_sample(store: Path, tmp_path: Path, workers: int) -> None:
    bad, tokens = _corrupt_copy(store, tmp_path)
    loader = make_loader(LoaderConfig(store=bad, batch_size=2, sample=SMALL), num_workers=workers)
    with pytest.raises(OccDataError, match="corrupt store data in labels/semantics for sample") as info:
        _indices(loader)
    assert any(t in str(info.value) for t in tokens)


def test_show_batch_cli(store: Path, tmp_path: Path) -> None:
    from click.testing import CliRunner

    from cli.fastocc_cli import main

    out = tmp_path / "b.png"
    r = CliRunner().invoke(main, ["show-batch", "--store", str(store), "--out", str(out), "-i", "1", "--train"])
    assert r.exit_code == 0, r.output
    img = __import__("cv2").imread(str(out))
    assert img.shape[1] == 3 * 704 and img.std() > 20
    r = CliRunner().invoke(main, ["show-batch", "--store", str(store), "--out", str(out), "-i", "4"])
    assert r.exit_code != 0 and "failed to build" in r.output
