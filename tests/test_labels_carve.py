"""Free-space carving (`occdata.labels.carve`, `occdata labels --boxes none`): the kernels against their
numpy twins, hand-made rays with hand-worked counts, a synthetic world labelled with its boxes withheld
(scored against its exact truth), and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from reference.labels_carve import carve_reference, dynamic_reference, gone_reference, slot_evidence

from occdata.errors import OccDataError
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.labels.carve import MAX_SLOTS, CarveGrid, CarveOptions, dynamic_points, sweep_slots
from occdata.labels.carving import sweep_keys
from occdata.labels.heights import GroundMap, ground_cells, ground_map
from occdata.labels.score import score_tree
from occdata.nuscenes import load_nuscenes

# The hand-worked figures below are for 0.2 m voxels and a 0.2 m graze height.
OPTS = CarveOptions(voxel_size=0.2, graze_height=0.2)


# ------------------------------------------------------------------------------------------------
# numba == numpy twin
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("seed", "near"), [(0, 0), (1, 1), (2, 2), (3, 1)])
def test_carve_matches_twin(seed: int, near: int) -> None:
    rng = np.random.default_rng(seed)
    opts = CarveOptions(voxel_size=0.5, margin=0.3, graze_max=2.0, graze_height=0.4, near=near)
    lo, hi = np.array([-1.0, -1.0, -0.5]), np.array([5.0, 4.5, 2.0])
    grid = CarveGrid(lo, hi, opts)
    slots = []
    for s in range(4):
        n_lidars = int(rng.integers(1, 3))  # few returns: with `near` 2 each blocks up to 125 voxels
        frames = [(rng.uniform(lo, hi), rng.uniform(lo - 0.5, hi + 0.5, (12, 3))) for _ in range(n_lidars)]
        slots.append(frames)
        grid.add_slot(s, frames)
    hits, crossed = carve_reference(slots, grid.lower, opts.voxel_size, grid.shape, opts.margin, opts.graze_max,
                                    opts.graze_height, near)
    assert crossed.sum() > 10 and hits.sum() > 20, "the rays must reach the grid for this to mean anything"
    np.testing.assert_array_equal(grid.hits, hits)
    np.testing.assert_array_equal(grid.crossed, crossed)
    before, after = gone_reference(slot_evidence(slots, grid.lower, opts.voxel_size, grid.shape, opts.margin,
                                                 opts.graze_max, opts.graze_height, near))
    seen = hits > 0  # `before` and `after` mean something only where a slot had a return
    np.testing.assert_array_equal(grid.before[seen], before[seen])
    np.testing.assert_array_equal(grid.after[seen], after[seen])
    pts = rng.uniform(lo - 0.5, hi + 0.5, (200, 3))
    for min_frames, ratio, min_gone in ((1, 0.5, 0), (2, 1.0, 0), (2, 1.0, 1), (3, 2.0, 2)):
        np.testing.assert_array_equal(
            dynamic_points(pts, grid.lower, opts.voxel_size, grid.shape, grid.hits, grid.crossed, min_frames, ratio,
                           grid.before, grid.after, min_gone),
            dynamic_reference(pts, grid.lower, opts.voxel_size, grid.shape, hits, crossed, min_frames, ratio,
                              before, after, min_gone))


def test_carve_matches_twin_over_hundreds_of_slots() -> None:
    """300 slots, each a wall return in one voxel and two random rays across a small grid: the counts
    pass 255 (where uint8 counters stopped) and the kernels still agree with the twin, which never caps."""
    rng = np.random.default_rng(7)
    opts = CarveOptions(voxel_size=0.5, margin=0.3, graze_max=1.0, graze_height=0.2, near=0)
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([3.0, 2.0, 1.0])
    grid = CarveGrid(lo, hi, opts)
    slots = []
    for s in range(300):
        wall = np.array([2.75, 1.25, 0.25]) + rng.uniform(-0.2, 0.2, 3)
        frames = [(np.array([-2.0, 1.0, 0.5]) + rng.uniform(-0.5, 0.5, 3),
                   np.vstack([wall, rng.uniform([2.5, 0.0, 0.0], [3.0, 2.0, 1.0], (2, 3))]))]
        slots.append(frames)
        grid.add_slot(s, frames)
    hits, crossed = carve_reference(slots, grid.lower, opts.voxel_size, grid.shape, opts.margin, opts.graze_max,
                                    opts.graze_height, 0)
    assert hits.max() > 255 and crossed.max() > 255, "the counts must pass uint8's 255 for this to mean anything"
    np.testing.assert_array_equal(grid.hits, hits)
    np.testing.assert_array_equal(grid.crossed, crossed)
    before, after = gone_reference(slot_evidence(slots, grid.lower, opts.voxel_size, grid.shape, opts.margin,
                                                 opts.graze_max, opts.graze_height, 0))
    seen = hits > 0
    np.testing.assert_array_equal(grid.before[seen], before[seen])
    np.testing.assert_array_equal(grid.after[seen], after[seen])
    pts = rng.uniform(lo, hi, (300, 3))
    np.testing.assert_array_equal(
        grid.dynamic(pts), dynamic_reference(pts, grid.lower, opts.voxel_size, grid.shape, hits, crossed,
                                             opts.min_frames, opts.ratio, before, after, opts.min_gone))


def _flat_ground(lo: np.ndarray, hi: np.ndarray, z: float = 0.0) -> GroundMap:
    """A ground map at height `z` over the box `[lo, hi]` (x, y): two returns per 0.5 m column."""
    x, y = np.meshgrid(np.arange(lo[0] - 1, hi[0] + 1, 0.2), np.arange(lo[1] - 1, hi[1] + 1, 0.2), indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    return ground_map([ground_cells(pts, np.array([*(lo[:2] + hi[:2]) / 2, z]), reach=1e3)], np.zeros(1))


@pytest.mark.parametrize(("seed", "near"), [(4, 1), (5, 2)])
def test_carve_near_above_ground_matches_twin(seed: int, near: int) -> None:
    """Slots with returns on a flat ground (their near rule reaching `near_above_ground` 0 voxels up) and
    above it (`near` all round): the kernels agree with the twin, and the ground returns shield fewer
    voxels than with the rule all round, so more are crossed."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-1.0, -1.0, -0.5]), np.array([5.0, 4.5, 2.0])
    ground = _flat_ground(lo, hi)
    grids = {up: CarveGrid(lo, hi, CarveOptions(voxel_size=0.5, margin=0.3, graze_max=2.0, graze_height=0.4,
                                                near=near, near_above_ground=up), ground=ground)
             for up in (0, near)}
    slots = []
    for s in range(4):
        on_road = np.c_[rng.uniform(lo[:2], hi[:2], (6, 2)), rng.uniform(0.0, 0.15, 6)]
        above = rng.uniform([lo[0], lo[1], 0.6], hi, (6, 3))
        frames = [(np.array([2.0, 1.5, 1.8]) + rng.uniform(-0.5, 0.5, 3), np.vstack([on_road, above]))]
        slots.append(frames)
        for g in grids.values():
            g.add_slot(s, frames)
    g = grids[0]
    assert g.on_ground(slots[0][0][1]).tolist() == [True] * 6 + [False] * 6
    hits, crossed = carve_reference(slots, g.lower, 0.5, g.shape, 0.3, 2.0, 0.4, near,
                                    lambda pts: np.where(g.on_ground(pts), 0, near))
    np.testing.assert_array_equal(g.hits, hits)
    np.testing.assert_array_equal(g.crossed, crossed)
    old = grids[near]
    np.testing.assert_array_equal(old.crossed, carve_reference(slots, g.lower, 0.5, g.shape, 0.3, 2.0, 0.4, near)[1])
    assert (g.crossed >= old.crossed).all() and g.crossed.sum() > old.crossed.sum()


# ------------------------------------------------------------------------------------------------
# hand-made rays
# ------------------------------------------------------------------------------------------------
def _grid(opts: CarveOptions = OPTS) -> CarveGrid:
    return CarveGrid(np.array([-1.0, -2.0, -1.0]), np.array([40.0, 2.0, 3.0]), opts)


def test_a_point_other_times_saw_through_is_dynamic() -> None:
    """A car at x = 10 m in slot 0; in slots 1 and 2 level rays (sensor at 1 m) pass x = 10 and end on a
    wall at x = 30. The car's point is crossed by 2 slots and hit by 1: dynamic; the wall, hit by all
    three (slot 0 sees it beside the car), is not."""
    g = _grid()
    origin = np.array([0.0, 0.0, 1.0])
    car, wall, wall_beside = np.array([[10.0, 0.0, 1.0]]), np.array([[30.0, 0.0, 1.0]]), np.array([[30.0, 0.5, 1.0]])
    g.add_slot(0, [(origin, np.vstack([car, wall_beside]))])
    g.add_slot(1, [(origin, np.vstack([wall, wall_beside]))])
    g.add_slot(2, [(origin, np.vstack([wall, wall_beside]))])
    assert g.dynamic(car).tolist() == [True]
    assert g.dynamic(np.vstack([wall, wall_beside])).tolist() == [False, False]
    i = np.floor((car[0] - g.lower) / OPTS.voxel_size).astype(int)
    assert (g.hits[tuple(i)], g.crossed[tuple(i)]) == (1, 2)
    # the same with one crossing slot: not enough evidence (min_frames 2)
    g1 = _grid()
    g1.add_slot(0, [(origin, car)])
    g1.add_slot(1, [(origin, wall)])
    assert g1.dynamic(car).tolist() == [False]


def _bus_side(late_hit: bool, min_gone: int) -> bool:
    """Slots 0-9 hit x = 10 m (a bus's side passing, 0.3 m a slot); slots 10-14 see through it to a wall at
    x = 30 m; with `late_hit` slot 15 hits x = 10 m again. Whether the x = 10 m point is dynamic."""
    g = _grid(CarveOptions(voxel_size=0.2, graze_height=0.2, min_gone=min_gone))
    origin = np.array([0.0, 0.0, 1.0])
    side, wall = np.array([[10.0, 0.0, 1.0]]), np.array([[30.0, 0.0, 1.0]])
    for s in range(16 if late_hit else 15):
        g.add_slot(s, [(origin, side if s < 10 or s == 15 else wall)])
    i = tuple(np.floor((side[0] - g.lower) / 0.2).astype(int))
    assert (g.hits[i], g.crossed[i], g.before[i], g.after[i]) == ((11, 5, 0, 0) if late_hit else (10, 5, 0, 5))
    return bool(g.dynamic(side)[0])


def test_a_long_mover_that_left_is_dynamic() -> None:
    """A voxel a long mover filled for 10 slots and 5 later slots saw empty: 5 crossings are fewer than 10
    hits (the ratio rule keeps it), but the last 5 slots that looked saw it empty (`min_gone` 4):
    what was there left. Filled again in a last slot, it is static: nothing left for good."""
    assert _bus_side(late_hit=False, min_gone=0) is False
    assert _bus_side(late_hit=False, min_gone=4) is True
    assert _bus_side(late_hit=False, min_gone=6) is False
    assert _bus_side(late_hit=True, min_gone=4) is False


def test_a_mover_that_arrived_is_dynamic() -> None:
    """Slots 0-4 see through x = 10 m to a wall; slots 5-14 hit x = 10 m: `before` is 5, the thing came."""
    g = _grid(CarveOptions(voxel_size=0.2, graze_height=0.2, min_gone=4))
    origin = np.array([0.0, 0.0, 1.0])
    car, wall = np.array([[10.0, 0.0, 1.0]]), np.array([[30.0, 0.0, 1.0]])
    for s in range(15):
        g.add_slot(s, [(origin, wall if s < 5 else car)])
    i = tuple(np.floor((car[0] - g.lower) / 0.2).astype(int))
    assert (g.hits[i], g.crossed[i], g.before[i], g.after[i]) == (10, 5, 5, 0)
    assert g.dynamic(car).tolist() == [True]


def test_grazing_rays_do_not_carve_the_ground() -> None:
    """A ray from 1.8 m onto the ground at x = 30 m (sin 0.06) passes 0.12 m over the ground at x = 28 m,
    inside the ground's 0.2 m voxel. Its last 0.2 / 0.06 = 3.3 m (graze_height 0.2 m) are no evidence, so
    a ground point there stays static; with the cut fixed at 0.4 m (graze_max = margin) the grazing rays
    carve it."""
    origin = np.array([0.0, 0.0, 1.8])
    ground_far, ground = np.array([[30.0, 0.0, 0.01]]), np.array([[28.0, 0.0, 0.01]])
    for opts, expect in ((OPTS, False), (CarveOptions(voxel_size=0.2, graze_height=0.2, graze_max=0.4), True)):
        g = _grid(opts)
        g.add_slot(0, [(origin, ground)])
        g.add_slot(1, [(origin, ground_far)])
        g.add_slot(2, [(origin, ground_far)])
        assert g.dynamic(ground).tolist() == [expect], opts


def test_a_slot_that_hits_a_voxel_gives_it_no_free_evidence() -> None:
    """Two rays of one slot: one ends in a voxel, another passes through it. That slot saw the voxel
    occupied and crossed at once (partly filled): it counts as a hit, not as a crossing."""
    g = _grid()
    origin = np.array([0.0, 0.0, 1.0])
    g.add_slot(0, [(origin, np.array([[10.05, 0.0, 1.0], [30.0, 0.0, 1.0]]))])
    i = np.floor((np.array([10.05, 0.0, 1.0]) - g.lower) / OPTS.voxel_size).astype(int)
    assert (g.hits[tuple(i)], g.crossed[tuple(i)]) == (1, 0)
    j = np.floor((np.array([5.0, 0.0, 1.0]) - g.lower) / OPTS.voxel_size).astype(int)
    assert g.crossed[tuple(j)] == 1, "one slot counts once however many of its rays cross"
    with pytest.raises(ValueError, match="twice"):
        g.add_slot(0, [])
    with pytest.raises(ValueError, match="time order"):
        g.add_slot(1, [])
        g.add_slot(0, [])  # slots come in time order: `before` and `after` depend on it


def test_rays_along_their_own_returns_are_no_evidence() -> None:
    """A wall along y = 0.3 m is seen at a slant. Slot 0 has a return on it at (10.1, 0.3). Slots 1 and 2,
    whose poses put the wall 0.2 m nearer (y = 0.1), return at (10.1, 0.1) and cast a level ray to
    (20, 0.62) that passes (10.1, 0.3)'s voxel ([10.0, 10.2] x [0.2, 0.4]) at y = 0.31-0.32. With `near` 1
    that voxel is next to the slots' own return's voxel ([0.0, 0.2] in y) and gets no evidence: the wall
    point stays static. With `near` 0 both slots cross it and it is taken for a mover."""
    origin = np.array([0.0, 0.0, 1.0])
    wall0, own, through = np.array([[10.1, 0.3, 1.0]]), np.array([[10.1, 0.1, 1.0]]), np.array([[20.0, 0.62, 1.0]])
    for near, expect in ((1, False), (0, True)):
        g = _grid(CarveOptions(voxel_size=0.2, graze_height=0.2, near=near))
        g.add_slot(0, [(origin, wall0)])
        g.add_slot(1, [(origin, np.vstack([own, through]))])
        g.add_slot(2, [(origin, np.vstack([own, through]))])
        i = np.floor((wall0[0] - g.lower) / 0.2).astype(int)
        assert (g.hits[tuple(i)], g.crossed[tuple(i)]) == (1, 0 if near else 2), near
        assert g.dynamic(wall0).tolist() == [expect], near


def test_a_car_over_the_road_is_carved_though_the_road_is_returned_under_it() -> None:
    """A car's lower body at (10, 0, 0.45) over a flat road (z = 0), seen by slot 0 from a LiDAR at 1.8 m.
    Slots 1 and 2 return on the road under it, (10, 0, 0): voxel [-0.1, 0.2] in z, the car's is the next
    one up, [0.2, 0.5]. Each also casts a ray onto the road at x = 13.33 m, which passes x = 9.8-10.1 at
    z = 0.48-0.44 (inside the car's voxel) and is cut 0.3 / sin = 2.24 m short of its return (x = 11.1).
    The near rule all round (`near_above_ground` 1) shields the voxel over the slots' road return: no
    evidence, the car stays static (Lyft's open-road smear). Reaching 0 voxels up over ground returns,
    both slots count: crossed 2 >= hits 1, dynamic. A point 0.15 m over the road stays static either
    way (ground rule)."""
    lo, hi = np.array([-1.0, -2.0, -1.0]), np.array([40.0, 2.0, 3.0])
    origin = np.array([0.0, 0.0, 1.8])
    car, wheel = np.array([[10.0, 0.0, 0.45]]), np.array([[10.0, 0.0, 0.15]])
    empty_road = np.array([[10.0, 0.0, 0.0], [13.33, 0.0, 0.0]])
    for up, expect in ((1, False), (0, True)):
        g = CarveGrid(lo, hi, CarveOptions(near=1, near_above_ground=up), ground=_flat_ground(lo, hi))
        g.add_slot(0, [(origin, car)])
        g.add_slot(1, [(origin, empty_road)])
        g.add_slot(2, [(origin, empty_road)])
        i = np.floor((car[0] - g.lower) / 0.3).astype(int)
        assert (g.hits[tuple(i)], g.crossed[tuple(i)]) == (1, 2 if expect else 0), up
        assert g.dynamic(car).tolist() == [expect], up
        assert g.dynamic(wheel).tolist() == [False], up


def test_hundreds_of_slots_never_saturate() -> None:
    """A wall point returned by 400 slots and crossed by 260 others (level rays past it to x = 38 m; their
    last 5 m, `graze_max`, are no evidence) is static: 260 < 400. Counters that stopped at 255 read
    255 >= 255 and turned it dynamic. The mirror case, a mover's point returned by 260 slots and
    crossed by 400, is dynamic. (The ratio rule alone, `min_gone` 0: the crossings here all come after the
    returns, which the `min_gone` rule reads as a thing that left.)"""
    origin = np.array([0.0, 0.0, 1.0])
    point, beyond = np.array([[30.0, 0.0, 1.0]]), np.array([[38.0, 0.0, 1.0]])
    i = tuple(np.floor((point[0] - _grid().lower) / OPTS.voxel_size).astype(int))
    for n_hit, n_cross, expect in ((400, 260, False), (260, 400, True)):
        g = _grid(CarveOptions(voxel_size=0.2, graze_height=0.2, min_gone=0))
        for s in range(n_hit + n_cross):
            g.add_slot(s, [(origin, point if s < n_hit else beyond)])
        assert (int(g.hits[i]), int(g.crossed[i])) == (n_hit, n_cross)
        assert g.dynamic(point).tolist() == [expect]
    with pytest.raises(ValueError, match="given twice"):
        g.add_slot(MAX_SLOTS, [])


def _frames(lidar_offsets_us: tuple[int, ...], samples: int, sweeps: int, period_us: int) -> list:
    """`scene_frames`-like frames (sample, LiDAR, record with a timestamp): keyframes 500 ms apart, then
    each LiDAR's `sweeps` sweeps before each keyframe, `period_us` apart; LiDAR k fires `lidar_offsets_us[k]`
    after the first."""
    key = [(i, k, SimpleNamespace(timestamp=500_000 * i + dt)) for i in range(samples)
           for k, dt in enumerate(lidar_offsets_us)]
    sweep = [(i, k, SimpleNamespace(timestamp=500_000 * i + dt - n * period_us)) for i in range(samples)
             for k, dt in enumerate(lidar_offsets_us) for n in range(1, sweeps + 1)]
    return key + sweep


def test_lidars_30_ms_apart_make_one_slot_per_sweep() -> None:
    """Two LiDARs, the second firing 30 ms after the first, at 10 Hz: each keyframe's two frames are one
    slot, and so is each pair of n-th sweeps; two sweeps of one LiDAR never share one. Slots are
    numbered in time order."""
    frames = _frames((0, 30_000), samples=2, sweeps=2, period_us=100_000)
    slots = sweep_slots(sweep_keys(frames, 4), [rec.timestamp for _, _, rec in frames])
    by_time = sorted(zip([rec.timestamp for _, _, rec in frames], slots.tolist(), strict=True))
    assert [s for _, s in by_time] == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5]
    assert sweep_keys(frames, 4)[:4] == [(0, 0), (0, 0), (1, 0), (1, 0)]
    # one LiDAR at 20 Hz (nuScenes): every frame its own slot, as before
    single = _frames((0,), samples=2, sweeps=9, period_us=50_000)
    assert len(set(sweep_slots(sweep_keys(single, 2), [r.timestamp for _, _, r in single]).tolist())) == 20


def test_a_lidar_30_ms_late_does_not_carve_what_its_sweep_mate_hit() -> None:
    """A wall at x = 30 m returned by LiDAR A at two keyframes; LiDAR B, 30 ms later in the same keyframes,
    sees past it (its ray ends at 38 m). As one slot per keyframe (`sweep_keys`) B's crossing is no evidence
    (its slot hit the voxel): static. As one slot per frame (a 10 ms window splits them) it is crossed by
    two slots and hit by two: dynamic."""
    frames = _frames((0, 30_000), samples=2, sweeps=0, period_us=100_000)
    rays = {0: (np.array([0.0, 0.0, 1.0]), np.array([[30.0, 0.0, 1.0]])),
            1: (np.array([0.0, 0.0, 1.0]), np.array([[38.0, 0.0, 1.0]]))}
    wall = rays[0][1]
    for slots, expect in ((sweep_slots(sweep_keys(frames, 4), [r.timestamp for _, _, r in frames]), False),
                          (np.arange(len(frames)), True)):
        g = _grid()
        for s in np.unique(slots):
            g.add_slot(int(s), [rays[frames[f][1]] for f in np.flatnonzero(slots == s)])
        assert g.dynamic(wall).tolist() == [expect]


def test_carve_options_validated() -> None:
    with pytest.raises(ValueError, match="margins"):
        CarveOptions(margin=2.0, graze_max=1.0)
    with pytest.raises(ValueError, match="min_frames"):
        CarveOptions(min_frames=MAX_SLOTS + 1)
    with pytest.raises(ValueError, match="near_above_ground"):
        CarveOptions(near=1, near_above_ground=2)
    with pytest.raises(ValueError, match="min_gone"):
        CarveOptions(min_gone=-1)
    with pytest.raises(ValueError, match="dynamic_class"):
        LabelOptions(dynamic_class=17)


# ------------------------------------------------------------------------------------------------
# a synthetic world with its boxes withheld
# ------------------------------------------------------------------------------------------------
WORLD = {"scenes": 1, "samples": 6, "seed": 11, "width": 320, "height": 180}


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from occdata.synth import SynthConfig, synthesize

    return synthesize(SynthConfig(out=tmp_path_factory.mktemp("carve") / "world", progress=False, **WORLD))


def _smear(world: Path, gen: Path) -> tuple[int, int]:
    from benchmarks.labels_carve import _score

    row = _score(world, gen, world / "gts", truth=True)
    return row["path_wrong"], row["path_free"]


def test_carving_keeps_precision_and_removes_smear(world: Path, tmp_path: Path) -> None:
    """Keyframes only, lidarseg: carving without boxes against the box-aware run and naive accumulation,
    scored on the world's exact truth (measured: precision 0.992, recall 0.764 vs 0.771, 79% of the
    naive path smear removed; 40 keyframes with sweeps: docs/labels.md)."""
    runs = {"boxes": LabelOptions(), "carve": LabelOptions(use_boxes=False, carve=True),
            "naive": LabelOptions(use_boxes=False, carve=False)}
    for name, opts in runs.items():
        generate_labels(LabelsConfig(root=world, out=tmp_path / name, options=opts, progress=False))
    boxes, carve = (score_tree(world, tmp_path / n, world / "gts").voxels for n in ("boxes", "carve"))
    assert carve.precision >= 0.95
    assert carve.recall >= boxes.recall - 0.03
    (w_carve, free), (w_naive, _) = _smear(world, tmp_path / "carve"), _smear(world, tmp_path / "naive")
    assert free > 1000 and w_naive > 500, "the world's movers must leave a naive smear for this to mean anything"
    assert w_carve <= 0.5 * w_naive
    manifest = json.loads((tmp_path / "carve" / "labels.json").read_text())
    assert manifest["carving"]["scenes"] == [load_nuscenes(world, None).scenes[0].name]
    assert "lidarseg classes" in manifest["carving"]["dynamic"]
    assert next(iter(manifest["scenes"].values()))["counts"]["mode"] == "carve"
    box_manifest = json.loads((tmp_path / "boxes" / "labels.json").read_text())
    assert "carving" not in box_manifest and "carve" not in box_manifest["options"]


def _copy_tree(world: Path, dst: Path) -> Path:
    """The world's tables copied, its data folders symlinked (so tables can be edited)."""
    dst.mkdir()
    for p in world.iterdir():
        if p.name != "v1.0-mini":
            (dst / p.name).symlink_to(p.resolve())
    shutil.copytree(world / "v1.0-mini", dst / "v1.0-mini")
    return dst


def test_no_boxes_without_lidarseg_states_the_dynamic_class(world: Path, tmp_path: Path) -> None:
    tree = _copy_tree(world, tmp_path / "tree")
    (tree / "v1.0-mini" / "lidarseg.json").unlink()
    for table in ("sample_annotation", "instance"):
        (tree / "v1.0-mini" / f"{table}.json").write_text("[]")
    out = tmp_path / "out"
    report = generate_labels(LabelsConfig(root=tree, out=out, options=LabelOptions(dynamic_class=7), progress=False))
    assert set(report.modes.values()) == {"carve"}, "a tree without box rows is carved by default"
    manifest = json.loads((out / "labels.json").read_text())
    assert manifest["carving"]["dynamic"].endswith("the tree has no lidarseg to say which")
    assert "7 (pedestrian)" in manifest["carving"]["dynamic"]
    sem = [np.load(p)["semantics"] for p in sorted(out.rglob("labels.npz"))]
    # 11: the ground from geometry (`--ground-class`, default driveable_surface)
    assert all(set(np.unique(s)) <= {0, 7, 11, 17} for s in sem) and any((s == 7).any() for s in sem)


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------
def test_boxes_for_some_scenes_only(tmp_path: Path) -> None:
    """Two scenes, one stripped of its boxes: that one is carved, the other keeps the box path, and the
    manifest says which."""
    from occdata.synth import SynthConfig, synthesize

    world = synthesize(SynthConfig(out=tmp_path / "w2", scenes=2, samples=2, seed=3, width=160, height=90,
                                   progress=False))
    tree = _copy_tree(world, tmp_path / "tree")
    ds = load_nuscenes(tree, None)
    bare = ds.scenes[1]
    vdir = tree / "v1.0-mini"
    anns = json.loads((vdir / "sample_annotation.json").read_text())
    gone = {a["instance_token"] for a in anns if a["sample_token"] in bare.sample_tokens}
    (vdir / "sample_annotation.json").write_text(json.dumps([a for a in anns if a["instance_token"] not in gone]))
    insts = json.loads((vdir / "instance.json").read_text())
    (vdir / "instance.json").write_text(json.dumps([i for i in insts if i["token"] not in gone]))
    report = generate_labels(LabelsConfig(root=tree, out=tmp_path / "out", progress=False))
    assert report.modes == {ds.scenes[0].name: "boxes", bare.name: "carve"}
    manifest = json.loads((tmp_path / "out" / "labels.json").read_text())
    assert manifest["carving"]["scenes"] == [bare.name]
    assert "mode" not in manifest["scenes"][ds.scenes[0].name]["counts"]


def test_one_keyframe_scene(tmp_path: Path) -> None:
    """Carving asked for a scene of one keyframe is refused in one line; by default (no boxes) the scene
    is labelled naively, which for one keyframe's own points smears nothing."""
    from occdata.synth import SynthConfig, synthesize

    world = synthesize(SynthConfig(out=tmp_path / "w1", scenes=1, samples=1, seed=4, width=160, height=90,
                                   progress=False))
    tree = _copy_tree(world, tmp_path / "tree")
    for table in ("sample_annotation", "instance"):
        (tree / "v1.0-mini" / f"{table}.json").write_text("[]")
    with pytest.raises(OccDataError, match=r"^scene \S+ has 1 keyframe: too short to carve") as e:
        generate_labels(LabelsConfig(root=tree, out=tmp_path / "a", progress=False,
                                     options=LabelOptions(use_boxes=False, carve=True)))
    assert "\n" not in str(e.value)
    report = generate_labels(LabelsConfig(root=tree, out=tmp_path / "b", progress=False))
    assert set(report.modes.values()) == {"naive"}


def test_lidar_files_without_returns(world: Path, tmp_path: Path) -> None:
    """A keyframe file whose every return lies on the ego car gives no rays and no points: handled (the
    scene is labelled). An empty file is refused in one line naming it."""
    tree = _copy_tree(world, tmp_path / "tree")
    (tree / "v1.0-mini" / "lidarseg.json").unlink()  # its labels would no longer match the file's points
    ds = load_nuscenes(tree, None)
    rec = ds.samples[2].lidar
    samples = tree / "samples"
    samples.unlink()
    shutil.copytree(world / "samples", samples)
    target = tree / Path(*rec.path.parts[rec.path.parts.index("samples"):])
    on_ego = np.zeros((3, 5), np.float32)  # the sensor's own position: inside the ego box
    target.chmod(0o644)
    target.write_bytes(on_ego.tobytes())
    opts = LabelOptions(use_boxes=False, carve=True)
    generate_labels(LabelsConfig(root=tree, out=tmp_path / "a", options=opts, progress=False))
    counts = next(iter(json.loads((tmp_path / "a" / "labels.json").read_text())["scenes"].values()))["counts"]
    assert counts["dropped_ego"] >= 3
    target.write_bytes(b"")
    with pytest.raises(OccDataError, match="corrupt LiDAR file .*0 bytes") as e:
        generate_labels(LabelsConfig(root=tree, out=tmp_path / "b", options=opts, progress=False))
    assert "\n" not in str(e.value)


LYFT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lyft-real"


@pytest.mark.slow
@pytest.mark.skipif(not LYFT.is_dir(), reason="the real Lyft keyframes are not in ../shared/data/lyft-real")
def test_real_lyft_tree_labels_end_to_end(tmp_path: Path) -> None:
    """The real Lyft keyframes (3 LiDARs, no boxes) label with no option: carved, every LiDAR's frames
    aggregated (16 keyframes x 3), some points dynamic, one label per keyframe (~20 s)."""
    report = generate_labels(LabelsConfig(root=LYFT, out=tmp_path / "out", progress=False))
    counts = next(iter(json.loads((tmp_path / "out" / "labels.json").read_text())["scenes"].values()))["counts"]
    assert set(report.modes.values()) == {"carve"}
    assert counts["frames"] == 48 and counts["keyframes"] == 16
    assert 0 < counts["dynamic_points"] < 0.5 * counts["points"]
    assert len(list((tmp_path / "out").rglob("labels.npz"))) == 16
