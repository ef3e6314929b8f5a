"""Issues 32/33: a worker holds only its task's rows, never the tables (bounded memory on nuScenes-size trees).

Two synthetic trees share the same two rendered scenes; the large one adds table-only scenes
(`occdata synth --table-only-scenes`). `build` and `labels` select the rendered scenes. The tests
take each task as the runner hands it over, pickle it as Dask would, and run it after the
version folder's tables are gone: a task that reads a table fails. Its pickled size must not
grow with the tables, and the outputs must not change.
"""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from test_store_build import store_digest

import occdata.labels.generate as labels_generate
import occdata.store.build as store_build
from cli.occdata_cli import main
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.labels.generate import load_inputs
from occdata.nuscenes import boxes_for_lidar, load_nuscenes
from occdata.nuscenes.summary import scan_tree
from occdata.runtime.cluster import ClusterConfig
from occdata.store.build import BuildConfig, build_store
from occdata.store.sample import SampleOptions
from occdata.synth import SynthConfig, synthesize

SPLITS = ("train", "val")
WORLD = {"scenes": 2, "samples": 2, "seed": 3, "width": 48, "height": 27, "table_only_samples": 4, "progress": False}
SMALL, LARGE = 2, 40  # table-only scenes besides the two rendered ones


@pytest.fixture(scope="module")
def trees(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """Table-only scene count -> a tree (same path length for both: pickled paths compare)."""
    base = tmp_path_factory.mktemp("bound")
    return {n: synthesize(SynthConfig(out=base / f"t{n:03d}", table_only_scenes=n, **WORLD)) for n in (SMALL, LARGE)}


class _Spy:
    """Stands in for `run_tasks` in a command's module: removes the tables, hands each task over
    pickled (as Dask does), records the pickled sizes, then runs them with the real runner."""

    def __init__(self, real: Any, tables: Path) -> None:
        self.real, self.tables, self.sizes = real, tables, []

    def __call__(self, client: Any, tasks: list[Any], **kw: Any) -> None:
        gone = self.tables.parent.parent / f"{self.tables.parent.name}-tables-gone"  # outside the tree
        shutil.move(self.tables, gone)
        shipped = []
        for task in tasks:
            blob = pickle.dumps(task)
            self.sizes.append(len(blob))
            shipped.append(pickle.loads(blob))  # noqa: S301 - our own tasks
        try:
            self.real(client, shipped, **kw)
        finally:
            shutil.move(gone, self.tables)


def _labels(tree: Path, out: Path, monkeypatch: pytest.MonkeyPatch, client: Any = None) -> _Spy:
    spy = _Spy(labels_generate.run_tasks, tree / "v1.0-mini")
    monkeypatch.setattr(labels_generate, "run_tasks", spy)
    generate_labels(LabelsConfig(root=tree, out=out, splits=SPLITS, options=LabelOptions(all_sweeps=True),
                                 progress=False), client)
    monkeypatch.undo()
    return spy


def _build(tree: Path, out: Path, monkeypatch: pytest.MonkeyPatch) -> _Spy:
    spy = _Spy(store_build.run_tasks, tree / "v1.0-mini")
    monkeypatch.setattr(store_build, "run_tasks", spy)
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", splits=SPLITS, block_samples=2, progress=False,
                            options=SampleOptions(lidar_sweeps=3)))
    monkeypatch.undo()
    return spy


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "labels.json"}


def test_labels_tasks_run_without_the_tables_and_do_not_grow(trees, tmp_path, monkeypatch) -> None:
    """Each scene task carries its scene's slice: it runs with the tables gone, its pickled size is
    the same for 4 and 42 scenes in the tree, and the labels are the bytes of a normal run."""
    spies = {n: _labels(trees[n], tmp_path / f"gen{n}", monkeypatch) for n in trees}
    assert len(spies[SMALL].sizes) == len(spies[LARGE].sizes) == 2
    assert max(spies[LARGE].sizes) <= max(spies[SMALL].sizes) + 64, (spies[SMALL].sizes, spies[LARGE].sizes)
    generate_labels(LabelsConfig(root=trees[SMALL], out=tmp_path / "plain", splits=SPLITS,
                                 options=LabelOptions(all_sweeps=True), progress=False))
    plain = _files(tmp_path / "plain")
    assert any(k.endswith("labels.npz") for k in plain)
    assert _files(tmp_path / f"gen{SMALL}") == plain
    assert _files(tmp_path / f"gen{LARGE}") == plain


def test_build_tasks_run_without_the_tables_and_do_not_grow(trees, tmp_path, monkeypatch) -> None:
    """The same for the build's convert tasks (a block's records): identical stores for both trees."""
    spies = {n: _build(trees[n], tmp_path / f"s{n}.zarr", monkeypatch) for n in trees}
    assert len(spies[SMALL].sizes) == len(spies[LARGE].sizes) == 2
    assert max(spies[LARGE].sizes) <= max(spies[SMALL].sizes) + 64, (spies[SMALL].sizes, spies[LARGE].sizes)
    plain = tmp_path / "plain.zarr"
    build_store(BuildConfig(root=trees[SMALL], out=plain, gts=trees[SMALL] / "gts", splits=SPLITS, block_samples=2,
                            progress=False, options=SampleOptions(lidar_sweeps=3)))
    want = store_digest(plain)
    assert store_digest(tmp_path / f"s{SMALL}.zarr") == want
    assert store_digest(tmp_path / f"s{LARGE}.zarr") == want


def test_dask_workers_never_read_the_tables(trees, tmp_path, monkeypatch) -> None:
    """On a 2-worker LocalCluster too (the old workers read every table in their first task)."""
    from occdata.runtime.cluster import cluster_client

    with cluster_client(ClusterConfig(workers=2)) as client:
        _labels(trees[SMALL], tmp_path / "dask", monkeypatch, client)
    _labels(trees[SMALL], tmp_path / "here", monkeypatch)
    assert _files(tmp_path / "dask") == _files(tmp_path / "here")


def test_scene_slice_gives_every_sweep_the_boxes_of_the_whole_tree(trees) -> None:
    """A slice holds one scene's samples, boxes and lidarseg paths, and the boxes at every LiDAR sweep
    (keyframes and the interpolated sweeps between them) are those the full dataset gives."""
    inputs, _ = load_inputs(LabelsConfig(root=trees[LARGE], out=Path("unused"), splits=SPLITS,
                                         options=LabelOptions(all_sweeps=True)))
    ds = inputs.dataset
    assert len(ds.scenes) == 2
    for scene in ds.scenes:
        part = inputs.for_scene(scene)
        assert [s.token for s in part.dataset.samples] == list(scene.sample_tokens)
        assert set(part.annotations.boxes_by_sample) <= set(scene.sample_tokens)
        assert len(part.lidarseg) == len(scene.sample_tokens)
        for k, token in enumerate(scene.sample_tokens):
            sample = ds.sample(token)
            for rec in (sample.lidar, *sample.sweeps):
                full = boxes_for_lidar(inputs.annotations, ds, ds.index_of(token), rec)
                mine = boxes_for_lidar(part.annotations, part.dataset, k, rec)
                assert [b.token for b in mine] == [b.token for b in full]
                for a, b in zip(mine, full, strict=True):
                    np.testing.assert_array_equal(a.center_global, b.center_global)
                    np.testing.assert_array_equal(a.rotation_wxyz, b.rotation_wxyz)


def test_table_only_scenes_scan_and_stay_out_of_the_selection(trees) -> None:
    """`--table-only-scenes` rows: a valid tree (scan), their own split, no file behind them."""
    summary = scan_tree(trees[LARGE], None, check_files=False)
    assert summary["scenes_per_split"]["table_only"] == LARGE
    assert summary["samples_per_split"]["table_only"] == LARGE * WORLD["table_only_samples"]
    assert summary["sweeps"]["per_keyframe_min"] == 9
    ds = load_nuscenes(trees[LARGE], sweeps=True).select(("table_only",))
    assert not any(c.path.exists() for s in ds.samples for c in s.cameras)
    small = load_nuscenes(trees[SMALL]).select(SPLITS)
    large = load_nuscenes(trees[LARGE]).select(SPLITS)
    assert [s.token for s in small.samples] == [s.token for s in large.samples]


def test_synth_cli_table_only_options(tmp_path) -> None:
    r = CliRunner().invoke(main, ["synth", "--out", str(tmp_path / "w"), "--scenes", "1", "--samples", "1",
                                  "--width", "16", "--height", "16", "--table-only-scenes", "3",
                                  "--table-only-samples", "2", "--no-progress"])
    assert r.exit_code == 0, r.output
    assert "(+ 3 table-only scenes)" in r.output
    assert scan_tree(tmp_path / "w", None, check_files=False)["samples_per_split"]["table_only"] == 6
    r = CliRunner().invoke(main, ["synth", "--out", str(tmp_path / "x"), "--table-only-scenes", "-1"])
    assert r.exit_code != 0 and "Traceback" not in r.output


def test_real_scene_slice_ships_its_boxes_and_sweeps(real_seq_root) -> None:
    """Real scene-0916 (41 keyframes, its sweep rows and 1,000+ boxes): the slice a task ships gives
    every LiDAR sweep the devkit-exact boxes of the full read, and pickles to well under a MB per
    keyframe's worth of rows."""
    inputs, _ = load_inputs(LabelsConfig(root=real_seq_root, out=Path("unused"),
                                         options=LabelOptions(all_sweeps=True)))
    (scene,) = inputs.dataset.scenes
    part = inputs.for_scene(scene)
    ds = inputs.dataset
    n_boxes = sum(len(b) for b in part.annotations.boxes_by_sample.values())
    assert n_boxes == sum(len(b) for b in inputs.annotations.boxes_by_sample.values()) > 1000
    assert part.annotations.instance_category.keys() <= inputs.annotations.instance_category.keys()
    n_sweeps = 0
    for k, sample in enumerate(part.dataset.samples):
        for rec in (sample.lidar, *sample.sweeps):
            n_sweeps += 1
            full = boxes_for_lidar(inputs.annotations, ds, ds.index_of(sample.token), rec)
            assert [(b.token, b.timestamp) for b in boxes_for_lidar(part.annotations, part.dataset, k, rec)] == [
                (b.token, b.timestamp) for b in full]
    assert n_sweeps > 10 * len(scene.sample_tokens) - 50  # ~10 LiDAR frames per keyframe at 20 Hz
    assert len(pickle.dumps(part)) < 2_000_000
