"""`occdata labels` on the Lyft- and TruckScenes-like synthetic worlds, scored against each world's exact
truth (`occdata.synth`'s voxelisation of its primitives): the labels are precise, every LiDAR of the rig
adds true occupied voxels (all LiDARs against the reference LiDAR alone, `--lidars`), and the truck's
grid (`benchmarks.labels_rigs.TRUCK_RANGE`, `--voxel-size 0.4 --range ...`) covers the truck and is
scored against the truth `occdata synth` writes on that grid. Tiny worlds; the figures at size are
`benchmarks/labels_rigs.py` (docs/labels.md, "Other rigs")."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from benchmarks.labels_rigs import TRUCK_FRONT_M, TRUCK_LENGTH_M, range_args, truck_grid
from cli.occdata_cli import main
from occdata.formats.gridfiles import read_grid_label
from occdata.formats.occ3d import label_path, read_label
from occdata.labels.score import score_tree
from occdata.nuscenes import load_nuscenes
from occdata.synth import SynthConfig, synthesize
from occdata.synth.rig import RIGS

SAMPLES = {"lyft": 3, "truckscenes": 2}


def _labels(args: list[str]) -> str:
    res = CliRunner().invoke(main, ["labels", "--no-progress", *args])
    assert res.exit_code == 0, res.output
    return res.output


@pytest.fixture(scope="module", params=sorted(SAMPLES))
def labelled(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A tiny world of the rig (the truck's also with its truth on the truck grid), labelled from every
    LiDAR ("all") and from the reference LiDAR alone ("ref")."""
    rig = request.param
    d = tmp_path_factory.mktemp(rig)
    world = d / "world"
    truck = rig == "truckscenes"
    synthesize(SynthConfig(out=world, scenes=1, samples=SAMPLES[rig], seed=3, width=96, height=54, progress=False,
                           rig=rig, grids=(truck_grid(),) if truck else ()))
    grids = ["--grid", "occ3d", *range_args()] if truck else []
    ref = RIGS[rig].reference.channel
    _labels(["--root", str(world), "--out", str(d / "all"), *grids])
    _labels(["--root", str(world), "--out", str(d / "ref"), "--lidars", ref, *grids])
    return {"rig": rig, "world": world, "dir": d, "ref": ref}


def test_labels_are_precise_and_every_lidar_adds(labelled: dict) -> None:
    world, d = labelled["world"], labelled["dir"]
    all_, ref = (score_tree(world, d / n, world / "gts") for n in ("all", "ref"))
    for t in (all_, ref):
        assert t.voxels.precision >= 0.9, t.voxels
        assert t.moving_total == 0 or t.moving_fraction >= 0.9  # movers stay in their boxes
    # The other LiDARs (Lyft's bumpers; the truck's five besides LIDAR_LEFT) find true voxels the
    # reference LiDAR alone does not.
    assert all_.voxels.true_positive > 1.1 * ref.voxels.true_positive, (all_.voxels, ref.voxels)
    assert all_.voxels.recall > ref.voxels.recall
    manifest = {n: json.loads((d / n / "labels.json").read_text()) for n in ("all", "ref")}
    assert manifest["all"]["rig"]["lidars"] == list(load_nuscenes(world, None).rig.lidars)
    assert manifest["ref"]["rig"]["lidars"] == [labelled["ref"]]


@pytest.mark.parametrize("labelled", ["truckscenes"], indirect=True)  # the truck grid is the truck's
def test_the_truck_grid_covers_the_truck_and_is_scored_on_its_truth(labelled: dict) -> None:
    spec = truck_grid()
    (x0, y0, z0), (x1, y1, z1) = spec.grid.lower, spec.grid.upper
    rear = TRUCK_FRONT_M - TRUCK_LENGTH_M  # the semi-trailer's tail, behind the tractor's rear axle
    assert x0 <= rear - 20.0 and x1 >= TRUCK_FRONT_M + 60.0  # the whole truck, traffic behind, braking room ahead
    mounts = np.array([c.calib.translation for c in (*RIGS["truckscenes"].cameras, *RIGS["truckscenes"].lidars)])
    assert (mounts >= [x0, y0, z0]).all() and (mounts < [x1, y1, z1]).all()
    assert z1 >= mounts[:, 2].max() + 2.0  # room above the roof sensors
    world, d = labelled["world"], labelled["dir"]
    ds = load_nuscenes(world, None)
    for s in ds.samples:  # the truth on the truck grid is the Occ3D truth where the two grids overlap
        occ = read_label(label_path(world / "gts", s.scene_name, s.token))["semantics"]
        big = read_grid_label(spec, label_path(world / "gts" / spec.name, s.scene_name, s.token))["semantics"]
        assert big.shape == spec.shape
        np.testing.assert_array_equal(big[:200, :, :16], occ)  # x -40..40, z -1..5.4 of both
        assert (big[200:] != 17).any()  # and it holds what lies beyond Occ3D's 40 m
    all_, ref = (score_tree(world, d / n / spec.name, world / "gts" / spec.name, spec) for n in ("all", "ref"))
    occ3d = score_tree(world, d / "all", world / "gts")
    assert all_.voxels.precision >= 0.9 and ref.voxels.precision >= 0.9
    assert all_.voxels.true_positive > max(ref.voxels.true_positive, occ3d.voxels.true_positive)


def test_split_file_and_lidar_choice(labelled: dict, tmp_path: Path) -> None:
    world = labelled["world"]
    scene = load_nuscenes(world, None).scenes[0].name
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"val": [scene]}))
    out = _labels(["--root", str(world), "--out", str(tmp_path / "val"), "--split-file", str(splits),
                   "--split", "val", "--scene", scene])
    assert "1 scene labelled" in out
    assert json.loads((tmp_path / "val" / "labels.json").read_text())["scene_splits"]["file"] == str(splits)
    res = CliRunner().invoke(main, ["labels", "--root", str(world), "--out", str(tmp_path / "bad"), "--lidars",
                                    "LIDAR_NOWHERE", "--no-progress"])
    assert res.exit_code != 0 and "LIDAR_NOWHERE" in res.output and len(res.output.strip().splitlines()) == 1
