"""Issue 48: `occdata verify` on Dask. The checksum tasks run in this process or on a 2-worker
LocalCluster; planted damage (a flipped byte in a label shard and in the JPEG bytes, a deleted depth
chunk) is found and named the same way by both, and by the CLI with `--scheduler`."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner
from replicated_tree import make_replicated_tree

from cli.occdata_cli import main
from occdata.errors import OccDataError
from occdata.runtime.cluster import ClusterConfig, cluster_client
from occdata.store.build import BuildConfig, build_store
from occdata.store.commands.verify import VerifyJob, verify_store
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
