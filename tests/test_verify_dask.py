"""Issue 48: `occdata verify` on Dask. The checksum tasks run in this process or on a 2-worker
LocalCluster; planted damage (a flipped byte in a label shard and in the JPEG bytes, a deleted depth
chunk) is found and named the same way by both, and by the CLI with `--scheduler`."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from replicated_tree import make_replicated_tree

from cli.occdata_cli import main
from occdata.errors import OccDataError
from occdata.runtime.cluster import ClusterConfig, cluster_client
from occdata.store.build import BuildConfig, build_store
from occdata.store.commands.verify import VerifyJob, first_absent_chunk, verify_store
from occdata.store.reader import open_store

N, BLOCK = 12, 4  # 3 blocks of 4 samples; a shard (labels) and a state chunk per block


@pytest.fixture(scope="module")
def good_store(real_nuscenes_root, real_occ3d_label, tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("vd")
    tree = make_replicated_tree(real_nuscenes_root, real_occ3d_label, base / "ns", 2, N // 2)
    out = base / "good.zarr"
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=BLOCK, progress=False))
    return out


@pytest.fixture(scope="module")
def client():
    with cluster_client(ClusterConfig(workers=2)) as c:
        yield c


def _flip(path: Path, frac: float) -> None:
    data = bytearray(path.read_bytes())
    data[int(len(data) * frac)] ^= 0x40
    path.write_bytes(bytes(data))


@pytest.fixture()
def damaged(good_store, tmp_path) -> Path:
    out = tmp_path / "bad.zarr"
    shutil.copytree(good_store, out)
    _flip(out / "labels/semantics/c/1/0/0/0", 0.6)  # the shard of samples 4..7
    _flip(out / "images/jpeg/c/0", 0.01)  # block 0's region starts with sample 0's first image
    last = max((out / "depth/uvd/c").iterdir(), key=lambda d: int(d.name))
    (last / "0").unlink()  # the last depth chunk: under the last block's points
    return out


def test_verify_finds_the_same_damage_in_this_process_and_on_two_workers(damaged, client) -> None:
    reader = open_store(damaged)
    here = verify_store(reader, task_samples=BLOCK)  # 3 tasks, run here
    there = verify_store(reader, client=client, task_samples=BLOCK)
    assert here == there
    by_array: dict[str, set[int]] = {}
    for p in here:
        by_array.setdefault(p.array, set()).add(p.index)
    assert by_array["labels/semantics"] and by_array["labels/semantics"] <= {4, 5, 6, 7}, here
    assert 0 in by_array["images/jpeg"], here
    assert any("is missing" in p.reason for p in here if p.array == "depth/uvd"), here
    assert all(p.token != "?" for p in here)


def test_a_clean_store_verifies_either_way(good_store, client) -> None:
    reader = open_store(good_store)
    assert verify_store(reader, task_samples=BLOCK) == [] == verify_store(reader, client=client, task_samples=8)


def test_cli_verify_on_a_scheduler_reports_what_one_process_does(damaged, client) -> None:
    runner = CliRunner()
    one = runner.invoke(main, ["verify", "--store", str(damaged), "--no-progress"])
    dask = runner.invoke(main, ["verify", "--store", str(damaged), "--no-progress",
                                "--scheduler", client.scheduler.address])
    assert one.exit_code == dask.exit_code == 1, (one.output, dask.output)
    lines = [ln for ln in one.output.splitlines() if ln.startswith("CORRUPT")]
    assert lines and lines == [ln for ln in dask.output.splitlines() if ln.startswith("CORRUPT")]


def test_a_verify_job_needs_a_sample_range() -> None:
    with pytest.raises(OccDataError, match="not a sample range"):
        VerifyJob("x.zarr", 5, 4)


def test_localcluster_workers_run_without_the_profiler_and_with_one_zarr_codec_thread(client) -> None:
    """Issue 48, where two workers' CPU went: Dask's statistical profiler off, zarr's codec pool at one
    thread (it starts cores + 4 by default), in every worker of our LocalCluster."""
    def settings() -> tuple[object, object]:
        import dask
        import zarr

        return dask.config.get("distributed.worker.profile.enabled"), zarr.config.get("threading.max_workers")

    assert set(client.run(settings).values()) == {(False, 1)}


def _first_absent_loop(offsets: np.ndarray, committed: np.ndarray, rows: int, absent: set[int]) -> list[int]:
    """The definition, one sample and camera at a time: the first camera range with an absent chunk
    under it, and its lowest absent chunk."""
    out = []
    for i in range(len(offsets)):
        first = -1
        for start, n in offsets[i] if committed[i] else ():
            gone = [k for k in range(start // rows, (start + n - 1) // rows + 1) if k in absent] if n > 0 else []
            if gone:
                first = gone[0]
                break
        out.append(first)
    return out


def test_first_absent_chunk_agrees_with_the_per_sample_loop() -> None:
    rng = np.random.default_rng(7)
    rows = 10
    for _ in range(50):
        n, cams = int(rng.integers(1, 9)), int(rng.integers(1, 4))
        starts = rng.integers(0, 200, size=(n, cams))
        lengths = rng.integers(-1, 40, size=(n, cams)) * (rng.random((n, cams)) > 0.2)
        offsets = np.stack([starts, lengths], axis=-1).astype(np.int64)
        committed = rng.random(n) > 0.2
        absent = np.unique(rng.integers(0, 25, size=int(rng.integers(0, 6))))
        got = first_absent_chunk(offsets, committed, rows, absent)
        assert got.tolist() == _first_absent_loop(offsets, committed, rows, set(absent.tolist()))


def test_first_absent_chunk_by_hand() -> None:
    offsets = np.array([[[0, 5], [25, 10]], [[40, 0], [95, 6]], [[5, 30], [0, 1]]], dtype=np.int64)
    # chunks of 10: sample 0 meets 0 and 2..3, sample 1 (40: empty) 9..10, sample 2 0..3 then 0
    got = first_absent_chunk(offsets, np.array([True, True, True]), 10, np.array([3, 10]))
    assert got.tolist() == [3, 10, 3]
    assert first_absent_chunk(offsets, np.array([True, False, True]), 10, np.array([4])).tolist() == [-1, -1, -1]


def test_present_chunks_parses_the_listing_as_the_chunk_keys_say(good_store) -> None:
    integrity = open_store(good_store).integrity
    for name in ("images/jpeg", "depth/uvd", "labels/semantics", "status/checksum", "images/offsets"):
        expected = np.flatnonzero(~integrity.absent_chunks(name))  # one key made per possible chunk
        assert integrity.present_chunks(name).tolist() == expected.tolist(), name


def test_a_deleted_jpeg_chunk_is_named_for_the_samples_over_it_by_every_task(good_store, client, tmp_path) -> None:
    out = tmp_path / "jpeg.zarr"
    shutil.copytree(good_store, out)
    reader = open_store(out)
    rows = reader.integrity.chunk_rows("images/jpeg")
    off = reader.group["images/offsets"][:]
    k = int(off[5, 2, 0]) // rows  # a chunk under sample 5's third image, in the middle block
    (out / "images/jpeg/c" / str(k)).unlink()
    expected = {i for i in range(N) if _first_absent_loop(off[i : i + 1], np.array([True]), rows, {k}) != [-1]}
    here = verify_store(open_store(out), task_samples=BLOCK)
    there = verify_store(open_store(out), client=client, task_samples=BLOCK)
    assert here == there
    missing = {p.index for p in here if p.array == "images/jpeg" and p.reason == f"chunk images/jpeg/c/{k} is missing"}
    assert 5 in missing and missing == expected, here
