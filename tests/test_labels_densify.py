"""Densification kernels (`occdata.labels.densify`): numba against their numpy twins, and hand-made
voxel grids with hand-worked results."""

from __future__ import annotations

import numpy as np
import pytest
from reference.labels_densify import (
    close_holes_reference,
    fill_behind_reference,
    fill_boxes_reference,
    seen_free_reference,
)

from occdata.constants import FREE_LABEL
from occdata.labels.densify import DEPTH_M, GAP_M, close_holes, densify, fill_behind, fill_boxes, seen_free, voxels_of

F = FREE_LABEL
LOWER = np.zeros(3)
ALL = np.arange(18) != F  # every occupied class eligible
SOLID = np.isin(np.arange(18), (0, 15, 16))


def _grid(shape: tuple[int, int, int]) -> np.ndarray:
    return np.full(shape, F, np.uint8)


def _random_semantics(rng: np.random.Generator, shape: tuple[int, int, int], p: float) -> np.ndarray:
    sem = rng.choice(np.array([0, 4, 11, 15, 16], np.uint8), size=shape)
    sem[rng.random(shape) > p] = F
    return sem


# ------------------------------------------------------------------------------------------------
# numba == numpy twin
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(3))
def test_seen_free_matches_twin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = np.array([7, 6, 5], np.int64)
    origins = rng.uniform(-1, 8, (40, 3))
    ends = rng.uniform(-1, 8, (40, 3))
    for margin in (0.0, 0.7):
        got = seen_free(origins, ends, LOWER, 1.0, shape, margin)
        assert got.any()
        np.testing.assert_array_equal(got, seen_free_reference(origins, ends, LOWER, 1.0, shape, margin))


@pytest.mark.parametrize("seed", range(3))
def test_fill_boxes_matches_twin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sem = _random_semantics(rng, (12, 11, 6), 0.2)
    free = (rng.random(sem.shape) < 0.2).astype(np.uint8)
    T = np.zeros((4, 4, 4))
    for b in range(4):
        yaw = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        T_grid_from_box = np.array([[c, -s, 0, rng.uniform(1, 4)], [s, c, 0, rng.uniform(1, 4)], [0, 0, 1, 1.0],
                                    [0, 0, 0, 1]])
        T[b] = np.linalg.inv(T_grid_from_box)
    half = rng.uniform(0.3, 1.5, (4, 3))
    got = fill_boxes(sem, free, T, half, LOWER, 0.4)
    assert (got >= 0).sum() > 10
    np.testing.assert_array_equal(got, fill_boxes_reference(sem, free, T, half, LOWER, 0.4))


@pytest.mark.parametrize("seed", range(3))
def test_fill_behind_matches_twin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sem = _random_semantics(rng, (14, 13, 3), 0.08)
    free = (rng.random(sem.shape) < 0.1).astype(np.uint8)
    origin = rng.uniform(-2, 7, 2)
    got = fill_behind(sem, free, SOLID, origin, 4, LOWER, 0.5)
    assert (got != sem).sum() > 10
    np.testing.assert_array_equal(got, fill_behind_reference(sem, free, SOLID, origin, 4, LOWER, 0.5))


@pytest.mark.parametrize("seed", range(3))
def test_close_holes_matches_twin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sem = _random_semantics(rng, (9, 8, 7), 0.5)
    free = (rng.random(sem.shape) < 0.1).astype(np.uint8)
    eligible = np.isin(np.arange(18), (4, 11, 15))
    for gap in (1, 2, 3):
        got = close_holes(sem, free, eligible, gap)
        assert (got != sem).any()
        np.testing.assert_array_equal(got, close_holes_reference(sem, free, eligible, gap))


# ------------------------------------------------------------------------------------------------
# hand-worked grids
# ------------------------------------------------------------------------------------------------
def test_seen_free_hand_worked() -> None:
    """1 m voxels; a ray along x at y = z = 0.5 from x = 0.5 to x = 3.5: it crosses voxels 0-2 and ends
    in 3. Cut 0 m short: 0, 1, 2 (never the end voxel 3); 1.6 m short (ends at x = 1.9): 0, 1; longer
    than the ray: nothing."""
    shape = np.array([5, 1, 1], np.int64)
    a, b = np.array([[0.5, 0.5, 0.5]]), np.array([[3.5, 0.5, 0.5]])
    assert seen_free(a, b, LOWER, 1.0, shape, 0.0)[:, 0, 0].tolist() == [1, 1, 1, 0, 0]
    assert seen_free(a, b, LOWER, 1.0, shape, 1.6)[:, 0, 0].tolist() == [1, 1, 0, 0, 0]
    assert seen_free(a, b, LOWER, 1.0, shape, 5.0)[:, 0, 0].tolist() == [0, 0, 0, 0, 0]


def test_hole_in_a_plane_is_filled_but_not_where_a_ray_saw_free() -> None:
    """Road plane z = 0 (class 11) with holes at (2, 2) and (5, 5): both are filled with 11 (road on both
    sides along x and y); when a ray saw (5, 5) free, that one stays free."""
    sem = _grid((8, 8, 3))
    sem[:, :, 0] = 11
    sem[2, 2, 0] = sem[5, 5, 0] = F
    free = np.zeros(sem.shape, np.uint8)
    out = close_holes(sem, free, ALL, 2)
    assert out[2, 2, 0] == 11 and out[5, 5, 0] == 11
    assert (out[:, :, 1:] == F).all(), "nothing above the plane"
    free[5, 5, 0] = 1
    out = close_holes(sem, free, ALL, 2)
    assert out[2, 2, 0] == 11 and out[5, 5, 0] == F


def test_corner_and_gap_between_parallel_walls_stay_free() -> None:
    """Ground (11) at z = 0 and a wall (15) at x = 0 rising to z = 3: the voxels in the corner (x = 1,
    z = 1) have occupied neighbours along x (the wall) and z (the ground) on one side only: not filled.
    Two walls at x = 3 and x = 5: the voxel x = 4 between them is flanked along x only: not filled. A hole
    in the wall (x = 0, y = 3, z = 2) is flanked along y and z: filled with 15."""
    sem = _grid((7, 7, 5))
    sem[:, :, 0] = 11
    sem[0, :, :4] = 15
    sem[0, 3, 2] = F
    sem[3, 1, 1:3] = sem[5, 1, 1:3] = 15
    out = close_holes(sem, np.zeros(sem.shape, np.uint8), ALL, 2)
    assert (out[1, :, 1:] == F).all()
    assert (out[4, 1, 1:] == F).all()
    assert out[0, 3, 2] == 15
    assert ((out != sem).sum()) == 1


def test_fill_behind_hand_worked() -> None:
    """Sensor at x = -1 on the row y = 0.5 (1 m voxels): a building voxel (15) at x = 2 fills x = 3..5
    (depth 3) and no farther; a ray that saw x = 4 free stops it after x = 3; a car (4) at x = 4 stops it
    too; a road voxel (11, not a solid) fills nothing."""
    sem = _grid((10, 1, 1))
    sem[2, 0, 0] = 15
    free = np.zeros(sem.shape, np.uint8)
    origin = np.array([-1.0, 0.5])
    row = fill_behind(sem, free, SOLID, origin, 3, LOWER, 1.0)[:, 0, 0]
    assert row.tolist() == [F, F, 15, 15, 15, 15, F, F, F, F]
    free[4, 0, 0] = 1
    assert fill_behind(sem, free, SOLID, origin, 3, LOWER, 1.0)[:, 0, 0].tolist()[:6] == [F, F, 15, 15, F, F]
    car = sem.copy()
    car[4, 0, 0] = 4
    assert fill_behind(car, np.zeros_like(free), SOLID, origin, 3, LOWER, 1.0)[:, 0, 0].tolist()[:7] == \
        [F, F, 15, 15, 4, F, F]
    road = _grid((10, 1, 1))
    road[2, 0, 0] = 11
    assert (fill_behind(road, np.zeros_like(free), SOLID, origin, 3, LOWER, 1.0) == road).all()


def test_densify_fills_a_closed_box_surface_not_what_rays_crossed() -> None:
    """A car (class 4) seen as the closed surface of a 5 x 5 x 4 voxel block (1 m voxels) whose box is
    annotated: its 3 x 3 x 2 inside is filled with 4. A ray from the sensor that crossed the inside (a
    gap in the skin) keeps the voxels it crossed free; the ground around stays as it was."""
    sem = _grid((12, 12, 6))
    sem[:, :, 0] = 11
    block = np.zeros(sem.shape, bool)
    block[3:8, 3:8, 1:5] = True
    inner = np.zeros(sem.shape, bool)
    inner[4:7, 4:7, 2:4] = True
    sem[block & ~inner] = 4
    T_box_from_grid = np.eye(4)
    T_box_from_grid[:3, 3] = -np.array([5.5, 5.5, 3.0])  # box centre (5.5, 5.5, 3.0)
    half = np.array([[2.5, 2.5, 2.0]])
    origin = np.array([0.5, 5.5, 2.5])
    far = np.array([[0.5, 0.5, 0.5]])  # a ray that crosses nothing of the car
    out, owner = densify(sem, origin, far, T_box_from_grid[None], half, np.array([4], np.uint8), LOWER, 1.0)
    assert (out[inner] == 4).all() and (owner[inner] == 0).all()
    assert (out[~inner] == sem[~inner]).all()
    # A ray through a gap in the near wall (x = 3) ending on the far wall (x = 7) at y = 5.5, z = 2.5.
    sem2 = sem.copy()
    sem2[3, 5, 2] = F
    ray_end = np.array([[7.5, 5.5, 2.5]])
    out2, _ = densify(sem2, origin, ray_end, T_box_from_grid[None], half, np.array([4], np.uint8), LOWER, 1.0)
    crossed = seen_free(origin[None], ray_end, LOWER, 1.0, np.array(sem.shape), 0.4)
    assert crossed[4:7, 5, 2].all()
    assert (out2[4:7, 5, 2] == F).all(), "voxels a ray crossed are never filled"
    assert out2[3, 5, 2] == F
    assert (out2[inner & (crossed == 0)] == 4).all()


def test_ground_hole_is_refused_only_by_a_ray_below_it() -> None:
    """Road (11) in layer z = 1 with a hole at (3, 3, 1), 1 m voxels, no boxes. A ray that grazes the road
    through the hole (at z = 1.5, ending at x = 7.5) does not stop the fill: the ground is a height field
    and a ray above it says nothing of its lower part. A ray under it (z = 0.5) does."""
    sem = _grid((8, 8, 3))
    sem[:, :, 1] = 11
    sem[3, 3, 1] = F
    none = (np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros(0, np.uint8))
    over = densify(sem, np.array([0.5, 3.5, 1.5]), np.array([[7.5, 3.5, 1.5]]), *none, LOWER, 1.0)[0]
    assert over[3, 3, 1] == 11 and (over != sem).sum() == 1
    under = densify(sem, np.array([0.5, 3.5, 0.5]), np.array([[7.5, 3.5, 0.5]]), *none, LOWER, 1.0)[0]
    assert (under == sem).all()


def test_densify_distances_are_metres_not_voxels() -> None:
    """GAP_M 0.8 m and DEPTH_M 2.8 m: 2 and 7 voxels at Occ3D's 0.4 m, twice as many at 0.2 m. A road
    plane (0.2 m voxels) with a 1.0 m hole is closed; at a 2-voxel gap (what a count in voxels
    gave on every grid) it stays open. A voxel is filled when occupied voxels lie within the gap on both
    sides along two axes: in a 5-voxel (1.0 m) hole along x, 3 voxels at a 4-voxel gap, none at 2."""
    assert (voxels_of(GAP_M, 0.4), voxels_of(DEPTH_M, 0.4)) == (2, 7)
    assert (voxels_of(GAP_M, 0.2), voxels_of(DEPTH_M, 0.2)) == (4, 14)
    assert voxels_of(GAP_M, 2.0) == 1
    sem = _grid((12, 12, 3))
    sem[:, :, 1] = 15  # a horizontal slab of manmade (not a ground class: the plain hole rule)
    sem[4:9, 5, 1] = F  # a 5-voxel hole along x (1.0 m)
    far = np.array([[0.1, 0.1, 0.1]])
    empty = (np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros(0, np.uint8))
    out, _ = densify(sem, np.array([1.2, 1.2, 0.5]), far, *empty, LOWER, 0.2, solids=False)
    assert (out[5:8, 5, 1] == 15).all() and out[4, 5, 1] == out[8, 5, 1] == F
    assert (close_holes(sem, np.zeros(sem.shape, np.uint8), ALL, 2)[4:9, 5, 1] == F).all()  # 2 voxels: open


def test_without_lidarseg_nothing_is_filled_behind_static_surfaces() -> None:
    """Labels without lidarseg give every static voxel one class (`--static-class`, default 0 `others`,
    which is a solid): the walk behind solids would fill under and beyond the road. With `solids=False`
    (what `occdata labels` passes when the scene has no lidarseg) only boxes and holes are filled."""
    sem = _grid((10, 1, 2))
    sem[:, 0, 0] = 0  # the road, labelled `others`
    sem[3, 0, 1] = 0  # a post
    far = np.array([[0.5, 0.5, 0.5]])
    empty = (np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros(0, np.uint8))
    filled, _ = densify(sem, np.array([0.5, 0.5, 1.5]), far, *empty, LOWER, 1.0)
    assert (filled[4:7, 0, 1] == 0).all()  # with solids: behind the post, `depth` voxels take its class
    kept, _ = densify(sem, np.array([0.5, 0.5, 1.5]), far, *empty, LOWER, 1.0, solids=False)
    np.testing.assert_array_equal(kept, sem)
