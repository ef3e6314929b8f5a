"""The synthetic truth on any grid (occdata.synth.gridtruth): the same rule as the Occ3D truth on a
level grid, the same world in the same place on a tilted (LiDAR-frame) grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference.synth_gridtruth import voxelize_tilted_reference

from occdata.constants import FREE_LABEL, GRID, OccGrid
from occdata.formats.gridspec import GRID_PRESETS
from occdata.geometry import transform_points
from occdata.synth.gridtruth import grid_semantics, level_frame, voxelize_tilted
from occdata.synth.labels import CLASS_PRIORITY, world_semantics
from occdata.synth.pipeline import ego_transform, keyframe_times, scene_world
from occdata.synth.rig import RIG


def _rot(axis: int, deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


@pytest.fixture(scope="module")
def world_at_key():
    world = scene_world(5, 0, 4)
    t = keyframe_times(0, 4)[2]
    return world, t, ego_transform(world, t)


def test_kernel_matches_its_numpy_twin() -> None:
    rng = np.random.default_rng(3)
    n = 40
    yaw = rng.uniform(-np.pi, np.pi, n)
    params = np.stack([rng.integers(0, 2, n).astype(float), rng.uniform(-4, 4, n), rng.uniform(-4, 4, n),
                       np.cos(yaw), np.sin(yaw), rng.uniform(0.05, 1.5, n), rng.uniform(0.05, 1.5, n),
                       rng.uniform(-2, 0, n), rng.uniform(0, 2, n)], 1)
    cls = rng.integers(0, 17, n).astype(np.int32)
    R = _rot(0, 3.0) @ _rot(1, -2.0) @ _rot(2, 30.0)
    sem = np.full((20, 20, 8), FREE_LABEL, np.uint8)
    lower = np.array([-4.0, -4.0, -1.6])
    fast = voxelize_tilted(sem, params, cls, CLASS_PRIORITY, R, lower, 0.4)
    ref = voxelize_tilted_reference(sem, params, cls, CLASS_PRIORITY, R, lower, 0.4)
    assert (fast != FREE_LABEL).sum() > 500
    np.testing.assert_array_equal(fast, ref)


@pytest.mark.parametrize("voxel_size", [0.4, 0.2])
def test_level_grid_equals_the_occ3d_truth(world_at_key, voxel_size: float) -> None:
    """A key-ego grid: exactly `world_semantics`, the other kernel (written per x slab, cubes only)."""
    world, t, T = world_at_key
    grid = OccGrid(GRID.lower, GRID.upper, voxel_size) if voxel_size != GRID.voxel_size else GRID
    prims = world.primitives_at(t)
    ours = grid_semantics(world.ground, prims, T, grid)
    assert (ours != FREE_LABEL).sum() > 10_000
    np.testing.assert_array_equal(ours, world_semantics(world.ground, prims, T, grid))


def test_turning_the_grid_turns_the_labels(world_at_key) -> None:
    """The grid frame turned by exactly 90 deg about z: the labels are the same array, turned."""
    world, t, T = world_at_key
    quarter = np.eye(4)
    quarter[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    prims = world.primitives_at(t)
    a = grid_semantics(world.ground, prims, T, GRID)
    b = grid_semantics(world.ground, prims, T @ quarter, GRID)
    # b's (x, y) is a's (-y, x): b[i, j] = a[X - 1 - j, i]
    np.testing.assert_array_equal(b, a[::-1].transpose(1, 0, 2))


def test_level_frame_keeps_origin_and_heading() -> None:
    T = np.eye(4)
    T[:3, :3] = _rot(2, 40.0) @ _rot(0, 1.5)
    T[:3, 3] = [10.0, -3.0, 1.8]
    T_level, R = level_frame(T)
    assert T_level[2, 0] == 0 and T_level[2, 2] == 1 and np.allclose(T_level[:3, 3], T[:3, 3])
    np.testing.assert_allclose(T_level[:3, :3] @ R, T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(math.degrees(math.atan2(T_level[1, 0], T_level[0, 0])), 40.0)


def test_lidar_grid_holds_the_world_where_the_key_ego_truth_does(world_at_key) -> None:
    """Each occupied SurroundOcc-grid voxel (LIDAR_TOP frame, tilted ~0.7 deg), taken to key ego, lands
    within one voxel of an occupied Occ3D-truth voxel of the same class (the Occ3D truth comes from the
    other kernel). The control treats the LiDAR frame as level and misses by more."""
    world, t, T_keyego = world_at_key
    spec, prims = GRID_PRESETS["surroundocc"], world.primitives_at(t)
    T_ego_from_lidar = RIG["LIDAR_TOP"].T_ego_from_sensor
    truth = world_semantics(world.ground, prims, T_keyego, GRID)

    def agreement(T_ego_from_grid: np.ndarray) -> float:
        sem = grid_semantics(world.ground, prims, T_keyego @ T_ego_from_grid, spec.grid)
        idx = np.argwhere(sem != FREE_LABEL)
        centres = np.asarray(spec.grid.lower) + (idx + 0.5) * spec.grid.voxel_size
        p = transform_points(T_ego_from_lidar, centres)  # the voxels as the LiDAR grid placed them
        v = np.floor((p - np.asarray(GRID.lower)) / GRID.voxel_size).astype(int)
        inside = ((v >= 1) & (v < np.array(GRID.shape) - 1)).all(1)
        v, cls = v[inside], sem[tuple(idx[inside].T)]
        hit = np.zeros(len(v), bool)
        for d in np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3):
            hit |= truth[tuple((v + d).T)] == cls
        return float(hit.mean())

    level = np.array(T_ego_from_lidar)
    level[:3, :3] = level_frame(T_ego_from_lidar)[0][:3, :3]  # the control: the tilt left out
    ours, control = agreement(T_ego_from_lidar), agreement(level)
    print(f"SurroundOcc truth voxels within one voxel of the Occ3D truth: {ours:.4f} (control {control:.4f})")
    assert ours >= 0.999, ours
    assert control < ours - 0.01, (control, ours)


def test_synth_writes_the_truth_on_every_preset(tmp_path) -> None:
    """`occdata synth --grid ...`: each grid's truth in its own layout, read back as its benchmark
    reads it; Occ3D's gts/ is the same bytes as without --grid; openocc-v2 is Occ3D's truth in its ids."""
    from click.testing import CliRunner

    from cli.occdata_cli import main
    from occdata.formats.gridfiles import LabelSite, grid_label_path, read_grid_label
    from occdata.formats.occ3d import read_label
    from occdata.nuscenes import load_nuscenes

    args = ["synth", "--scenes", "1", "--samples", "2", "--seed", "2", "--width", "64", "--height", "36",
            "--no-progress"]
    plain, grids = tmp_path / "plain", tmp_path / "grids"
    assert CliRunner().invoke(main, [*args, "--out", str(plain)]).exit_code == 0
    res = CliRunner().invoke(main, [*args, "--out", str(grids), *[x for g in GRID_PRESETS for x in ("--grid", g)],
                                    "--voxel-size", "0.8"])
    assert res.exit_code == 0, res.output
    occ3d_files = sorted(p.relative_to(plain / "gts") for p in (plain / "gts").rglob("labels.npz"))
    assert [(grids / "gts" / f).read_bytes() for f in occ3d_files] == [(plain / "gts" / f).read_bytes()
                                                                      for f in occ3d_files]
    assert not (grids / "gts" / "occ3d").exists()
    ds = load_nuscenes(grids, None)
    for s in ds.samples:
        site = LabelSite(s.scene_name, s.scene_token, s.token, s.lidar.token, s.lidar.path.name)
        occ3d = read_label(grids / "gts" / s.scene_name / s.token / "labels.npz")
        openocc = read_grid_label(GRID_PRESETS["openocc-v2"],
                                  grid_label_path(GRID_PRESETS["openocc-v2"], grids / "gts" / "openocc-v2", site))
        np.testing.assert_array_equal(openocc["semantics"], GRID_PRESETS["openocc-v2"].lut()[occ3d["semantics"]])
        np.testing.assert_array_equal(openocc["mask_camera"], occ3d["mask_camera"])
        for name in ("surroundocc", "openoccupancy"):
            spec = GRID_PRESETS[name]
            sem = read_grid_label(spec, grid_label_path(spec, grids / "gts" / name, site))["semantics"]
            assert sem.shape == spec.shape and (sem != 0).sum() > 1000  # 0: empty in the sparse layouts
        custom = np.load(grids / "gts" / "occ3d-0.8m" / s.scene_name / s.token / "labels.npz", allow_pickle=False)
        assert custom["semantics"].shape == (100, 100, 8) and custom["mask_camera"].any()
