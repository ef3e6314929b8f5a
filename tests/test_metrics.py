"""Occ3D mIoU and RayIoU (occdata.eval.metrics): hand-computed values, brute-force ray marching, twins."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference.eval_miou import confusion_matrix_reference
from reference.eval_rayiou import first_hits_reference

from occdata.constants import FREE_LABEL, GRID, OccGrid
from occdata.errors import OccDataError
from occdata.eval.metrics import (
    MIoUAccumulator,
    RayIoUAccumulator,
    confusion_matrix,
    first_hits,
    lidar_ray_directions,
    ray_counts,
    ray_origins_keyego,
    ray_pitches,
)

F = FREE_LABEL


def _grid(values: list[int]) -> np.ndarray:
    return np.array(values, np.uint8).reshape(len(values), 1, 1)


# --------------------------------------------------------------------------------------------------
# mIoU
# --------------------------------------------------------------------------------------------------
def test_miou_hand_case_without_mask() -> None:
    """gt [0, 0, 1, F], pred [0, 1, 1, F]: class 0 TP 1 FN 1 -> 1/2; class 1 TP 1 FP 1 -> 1/2;
    other semantic classes absent -> NaN, so mIoU = (1/2 + 1/2) / 2 = 0.5. Geometry: all 3 occupied
    truth voxels are predicted occupied and the free one free -> 1.0."""
    acc = MIoUAccumulator()
    acc.update(_grid([0, 0, 1, F]), _grid([0, 1, 1, F]))
    r = acc.result()
    assert r.per_class_iou[0] == 0.5 and r.per_class_iou[1] == 0.5 and r.per_class_iou[F] == 1.0
    assert np.isnan(r.per_class_iou[2:F]).all()
    assert r.miou == 0.5
    assert r.geo_iou == 1.0
    assert r.confusion[0, 1] == 1 and r.confusion.sum() == 4


def test_miou_hand_case_with_mask() -> None:
    """Same grids, the disagreeing voxel masked out: classes 0 and 1 are perfect -> mIoU 1.0."""
    acc = MIoUAccumulator()
    acc.update(_grid([0, 0, 1, F]), _grid([0, 1, 1, F]), mask=_grid([1, 0, 1, 1]))
    r = acc.result()
    assert r.per_class_iou[0] == 1.0 and r.per_class_iou[1] == 1.0
    assert r.miou == 1.0 and r.confusion.sum() == 3


def test_miou_class_only_in_prediction_scores_zero() -> None:
    """gt [F, F, 2, 2], pred [3, F, 2, F]: class 3 only predicted -> 0/1 = 0 (counts); class 2 TP 1
    FN 1 -> 1/2; mIoU = (0 + 1/2) / 2 = 0.25. Geometry: TP 1 (voxel 2), FP 1 (voxel 0), FN 1
    (voxel 3) -> 1/3."""
    acc = MIoUAccumulator()
    acc.update(_grid([F, F, 2, 2]), _grid([3, F, 2, F]))
    r = acc.result()
    assert r.per_class_iou[3] == 0.0 and r.per_class_iou[2] == 0.5
    assert r.miou == 0.25
    assert r.geo_iou == pytest.approx(1 / 3)


def test_miou_one_matrix_over_the_split_and_merge() -> None:
    """Sample A: gt [0, F] pred [0, F]; sample B: gt [4, 4] pred [4, F]. Split matrix: class 0
    1/1, class 4 TP 1 FN 1 -> 1/2; mIoU = 0.75 (not the mean of per-sample mIoUs, 1 and 0.5 ->
    also 0.75 here, so check the per-class value that only the split matrix gives: class 4 = 0.5).
    A batch update, a merge of two accumulators and a state round trip all give the same."""
    a_gt, a_pr = _grid([0, F]), _grid([0, F])
    b_gt, b_pr = _grid([4, 4]), _grid([4, F])
    one = MIoUAccumulator()
    one.update(a_gt, a_pr)
    one.update(b_gt, b_pr)
    r = one.result()
    assert r.per_class_iou[0] == 1.0 and r.per_class_iou[4] == 0.5 and r.miou == 0.75
    batch = MIoUAccumulator()
    batch.update(np.stack([a_gt, b_gt]), np.stack([a_pr, b_pr]))
    x, y = MIoUAccumulator(), MIoUAccumulator()
    x.update(a_gt, a_pr)
    y.update(b_gt, b_pr)
    merged = x.merge(y)
    restored = MIoUAccumulator.from_state(x.state)
    for other in (batch, merged, restored):
        np.testing.assert_array_equal(other.result().confusion, r.confusion)
    assert batch.n_samples == 2 and merged.n_samples == 2
    assert one.state.dtype == np.int64


def test_miou_no_semantic_class_anywhere_is_nan() -> None:
    acc = MIoUAccumulator()
    acc.update(_grid([F, F]), _grid([F, F]))
    r = acc.result()
    assert math.isnan(r.miou) and math.isnan(r.geo_iou) and r.per_class_iou[F] == 1.0


def test_miou_real_label_against_itself(real_occ3d_label) -> None:
    d = np.load(real_occ3d_label, allow_pickle=False)
    sem, cam = d["semantics"], d["mask_camera"]
    acc = MIoUAccumulator()
    acc.update(sem, sem, cam)
    r = acc.result()
    present = np.unique(sem[cam == 1])
    assert np.all(r.per_class_iou[present] == 1.0)
    absent = np.setdiff1d(np.arange(18), present)
    assert np.isnan(r.per_class_iou[absent]).all()
    assert r.miou == 1.0 and r.geo_iou == 1.0
    assert r.confusion.sum() == int(cam.sum())


@pytest.mark.parametrize("bad", ["pred18", "pred255", "gt255", "shape", "float"])
def test_miou_bad_inputs_raise(bad: str) -> None:
    gt, pred = _grid([0, 1, F]), _grid([0, 1, F])
    if bad == "pred18":
        pred[1] = 18
    elif bad == "pred255":
        pred[0] = 255
    elif bad == "gt255":
        gt[0] = 255
    elif bad == "shape":
        pred = _grid([0, 1])
    else:
        pred = pred.astype(np.float32)
    with pytest.raises(OccDataError):
        MIoUAccumulator().update(gt, pred)


def test_miou_out_of_range_prediction_is_an_error_even_where_masked() -> None:
    with pytest.raises(OccDataError, match="prediction"):
        MIoUAccumulator().update(_grid([0, 1]), _grid([0, 20]), mask=_grid([1, 0]))


def test_miou_unlabelled_truth_outside_the_mask_is_ignored() -> None:
    """gt [0, 255], pred [0, F], mask [1, 0]: the 255 voxel is masked out -> class 0 = 1/1."""
    acc = MIoUAccumulator()
    acc.update(_grid([0, 255]), _grid([0, F]), mask=_grid([1, 0]))
    r = acc.result()
    assert r.confusion.sum() == 1 and r.per_class_iou[0] == 1.0


def test_confusion_kernel_matches_numpy_twin() -> None:
    rng = np.random.default_rng(0)
    for _ in range(5):
        gt = rng.integers(0, 18, (3, 20, 20, 8)).astype(np.uint8)
        pred = rng.integers(0, 18, gt.shape).astype(np.uint8)
        mask = (rng.random(gt.shape) < 0.6).astype(np.uint8)
        np.testing.assert_array_equal(confusion_matrix(gt, pred, mask), confusion_matrix_reference(gt, pred, mask))
        np.testing.assert_array_equal(confusion_matrix(gt, pred), confusion_matrix_reference(gt, pred))


# --------------------------------------------------------------------------------------------------
# RayIoU: ray set and origins
# --------------------------------------------------------------------------------------------------
def test_ray_set_has_14040_rays_with_the_design_pitches() -> None:
    p = ray_pitches()
    assert len(p) == 39
    for k in range(10):
        assert p[k] == pytest.approx(-(math.pi / 2 - math.atan(k + 1)), abs=1e-15)
    step = p[9] - p[8]
    assert np.allclose(np.diff(p[9:]), step)
    assert p[-1] >= 0.21 > p[-2]
    d = lidar_ray_directions()
    assert d.shape == (14040, 3) and d.dtype == np.float32
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    # ray p * 360 + a: pitch p, azimuth a degrees
    i = 20 * 360 + 90
    assert d[i] == pytest.approx([0.0, math.cos(p[20]), math.sin(p[20])], abs=1e-6)
    assert np.allclose(np.arcsin(d[::360, 2]), p, atol=1e-6)


def _pose(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def test_origins_hand_made_poses_drop_far_and_subsample() -> None:
    """12 keyframes 5 m apart along global x, LiDAR 1 m ahead of and 2 m above the ego origin.
    Frame s's LiDAR origin in the ego of frame c is (5 (s - c) + 1, 0, 2). For c = 2, |x| < 39
    keeps s = 0..9 (s = 10 is at 41 m), 10 origins; np.round(np.linspace(0, 9, 8)) =
    [0, 1, 3, 4, 5, 6, 8, 9], so s = 2 (the current frame itself) is dropped: x = -9, -4, 6, 11, 16,
    21, 31, 36."""
    T_g = np.stack([_pose(0, (5.0 * s, 0, 0)) for s in range(12)])
    T_el = np.stack([_pose(0, (1.0, 0, 2.0))] * 12)
    o = ray_origins_keyego(T_g, T_el, 2)
    np.testing.assert_allclose(o, [[x, 0, 2] for x in (-9, -4, 6, 11, 16, 21, 31, 36)], atol=1e-9)
    assert o.dtype == np.float64


def test_origins_rotated_frames_and_lateral_cut() -> None:
    """Car heading global +y (yaw 90), LiDAR yawed -90 in the ego at (0.94, 0, 1.84); frames 10 m
    apart, frame 3 also 40 m to the car's right. In the ego of frame 1: frame s at
    (10 (s - 1) + 0.94, 0, 1.84); frame 3 at y = -40 is dropped (|y| >= 39); 3 frames remain, no
    subsampling. The current frame's own origin is exactly T_ego_from_lidar's translation."""
    T_g = np.stack([_pose(90, (0.0, 10.0 * s, 0)) for s in range(4)])
    T_g[3, :3, 3] = (40.0, 30.0, 0.0)  # 40 m along global +x = the car's right (ego -y)
    T_el = np.stack([_pose(-90, (0.94, 0.0, 1.84))] * 4)
    o = ray_origins_keyego(T_g, T_el, 1)
    np.testing.assert_allclose(o, [[-9.06, 0, 1.84], [0.94, 0, 1.84], [10.94, 0, 1.84]], atol=1e-5)
    assert np.array_equal(o[1], [0.94, 0.0, 1.84])


def test_origins_round_to_float32_in_the_lidar_frame() -> None:
    """A frame 0.1 m ahead: its LiDAR-frame offset is float32(0.1) (then moved into ego in float64)."""
    T_g = np.stack([_pose(0, (0.0, 0, 0)), _pose(0, (0.1, 0, 0))])
    T_el = np.stack([_pose(0, (1.0, 0, 2.0))] * 2)
    o = ray_origins_keyego(T_g, T_el, 0)
    assert o[1, 0] == float(np.float32(0.1)) + 1.0 != 1.1


# --------------------------------------------------------------------------------------------------
# RayIoU: ray casting
# --------------------------------------------------------------------------------------------------
def _random_scene(rng: np.random.Generator, shape: tuple[int, int, int], density: float) -> np.ndarray:
    lab = np.full(shape, F, np.uint8)
    occ = rng.random(shape) < density
    lab[occ] = rng.integers(0, 17, occ.sum())
    return lab


def _random_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d[: n // 10, 1] = 0.0  # some rays exactly in an axis plane (zero direction component)
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def test_first_hits_kernel_matches_numpy_twin() -> None:
    rng = np.random.default_rng(1)
    small = OccGrid(lower=(-2.0, -2.4, -0.8), upper=(2.8, 2.4, 1.6), voxel_size=0.4)
    for density in (0.02, 0.2):
        lab = _random_scene(rng, small.shape, density)
        origins = np.r_[rng.uniform(small.lower, small.upper, (3, 3)), [[-3.0, 0.1, 0.3]]]  # last: outside
        dirs = _random_dirs(rng, 500)
        d1, c1 = first_hits(lab, origins, dirs, grid=small)
        d2, c2 = first_hits_reference(lab, origins, dirs, grid=small)
        np.testing.assert_array_equal(c1, c2)
        np.testing.assert_array_equal(d1, d2)  # bitwise (NaN where no hit)
    # the protocol rays through a full-size grid
    lab = _random_scene(rng, GRID.shape, 0.01)
    o = np.array([[0.94, 0.0, 1.84], [-20.0, 13.0, 1.84]])
    d1, c1 = first_hits(lab, o)
    d2, c2 = first_hits_reference(lab, o)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(d1, d2)


def _march(lab: np.ndarray, grid: OccGrid, origin: np.ndarray, dirs: np.ndarray, step: float):
    """Brute force: sample o + t d for t = 0, step, 2 step, ...; the first sample inside an occupied
    voxel picks the voxel; the distance is the first sample past it (so d_true lies in
    (d - step, d]). Returns (dist (R,) float64, NaN no hit, cls (R,))."""
    lower = np.asarray(grid.lower)
    shape = np.array(grid.shape)
    d = dirs.astype(np.float64)
    n_steps = int(np.linalg.norm(np.asarray(grid.upper) - lower) / step) + 3
    t = np.arange(n_steps) * step
    pts = origin[None, None, :] + t[None, :, None] * d[:, None, :]  # (R, T, 3)
    idx = np.floor((pts - lower) / grid.voxel_size).astype(np.int64)
    inside = np.all((idx >= 0) & (idx < shape), axis=-1)
    ci = np.clip(idx, 0, shape - 1)
    lab_s = np.where(inside, lab[ci[..., 0], ci[..., 1], ci[..., 2]], F)
    occ = lab_s != F
    hit = occ.any(axis=1)
    first = np.argmax(occ, axis=1)
    R = len(d)
    rows = np.arange(R)
    hit_vox = idx[rows, first]
    same = np.all(idx == hit_vox[:, None, :], axis=-1) & (np.arange(n_steps)[None, :] >= first[:, None])
    # first sample after `first` that is outside the hit voxel
    after = ~same & (np.arange(n_steps)[None, :] > first[:, None])
    leave = np.argmax(after, axis=1)
    dist = np.where(hit, t[leave], np.nan)
    cls = np.where(hit, lab_s[rows, first], F)
    return dist, cls


def _agree_with_march(lab: np.ndarray, grid: OccGrid, origin: np.ndarray, dirs: np.ndarray, dist: np.ndarray,
                      cls: np.ndarray, steps: tuple[float, ...]) -> int:
    """Check (dist, cls) of each ray against marches of decreasing step: a ray agrees with a march
    of step h if the classes match and d_true in (d_march - h, d_march]. Rays that disagree with
    the coarse march (a voxel corner grazed over less than h) are re-checked with the next step;
    returns how many rays disagreed with the coarsest."""
    todo = np.arange(len(dirs))
    n_coarse = -1
    diag = float(np.linalg.norm(np.asarray(grid.upper) - np.asarray(grid.lower)))
    for h in steps:
        if todo.size == 0:
            break
        # grazing rays are rare: many left after the coarse march means a real disagreement
        assert n_coarse < 0 or todo.size <= 50, f"{todo.size} rays disagree with the coarse march"
        chunk = max(1, int(4e6 / (diag / h)))  # bounded memory: rays x samples per march
        agree = np.zeros(todo.size, bool)
        for lo in range(0, todo.size, chunk):
            sl = todo[lo: lo + chunk]
            bd, bc = _march(lab, grid, origin, dirs[sl], h)
            d = dist[sl]
            both_miss = np.isnan(bd) & np.isnan(d)
            close = (d <= bd + 1e-4) & (d > bd - h - 1e-4)
            agree[lo: lo + chunk] = (bc == cls[sl]) & (both_miss | close)
        todo = todo[~agree]
        if n_coarse < 0:
            n_coarse = int(todo.size)
    assert todo.size == 0, f"rays {todo[:10]} disagree even with a {steps[-1]} m march"
    return n_coarse


def test_first_hit_distances_equal_a_brute_force_march() -> None:
    """Random grids and rays: the DDA's (distance where the ray leaves the first occupied voxel,
    class) equals a 0.01 m march; the few rays that graze a voxel corner (chord < 0.01 m, missed by
    the coarse march) agree with a finer march (0.0005 m, then 0.00002 m)."""
    rng = np.random.default_rng(2)
    grid = OccGrid(lower=(-2.0, -2.0, -1.0), upper=(2.8, 2.8, 1.4), voxel_size=0.4)
    checked = 0
    for trial in range(4):
        lab = _random_scene(rng, grid.shape, 0.03 + 0.05 * trial)
        origin = rng.uniform(np.asarray(grid.lower) + 0.1, np.asarray(grid.upper) - 0.1)
        dirs = _random_dirs(rng, 400)
        dist, cls = first_hits(lab, origin[None], dirs, grid=grid)
        n_graze = _agree_with_march(lab, grid, origin, dirs, dist[0].astype(np.float64), cls[0],
                                    (0.01, 0.0005, 0.00002))
        assert n_graze < 0.02 * len(dirs)
        checked += int((cls[0] != F).sum())
    assert checked > 800  # the test saw many real hits


def test_protocol_rays_on_the_real_label_equal_a_brute_force_march(real_occ3d_label) -> None:
    """Full Occ3D grid ([-40, 40] x [-40, 40] x [-1, 5.4]), real label, the protocol's rays (every
    7th of 14,040) from a LiDAR-like origin: class and distance equal a 0.02 m march (grazing rays:
    finer marches)."""
    sem = np.load(real_occ3d_label, allow_pickle=False)["semantics"]
    origin = np.array([0.94, 0.13, 1.84])
    dirs = lidar_ray_directions()[::7]
    dist, cls = first_hits(sem, origin[None], dirs)
    dist, cls = dist[0].astype(np.float64), cls[0]
    assert (cls != F).sum() > 1000
    n_graze = _agree_with_march(sem, GRID, origin, dirs, dist, cls, (0.02, 0.0005, 0.0001))
    assert n_graze < 0.03 * len(dirs)  # 27 of 2006 here: shallow ground hits clip voxel corners


def test_rayiou_identical_grids_is_one_for_every_class_seen(real_occ3d_label) -> None:
    sem = np.load(real_occ3d_label, allow_pickle=False)["semantics"]
    origins = np.array([[0.94, 0.0, 1.84], [-12.0, 3.0, 1.84], [15.0, -2.0, 1.84]])
    acc = RayIoUAccumulator()
    acc.update(sem, sem, origins)
    r = acc.result()
    seen = r.counts[0, :F] > 0
    assert seen.sum() >= 5
    assert np.all(r.per_class[:, seen] == 1.0)
    assert np.isnan(r.per_class[:, ~seen]).all()
    assert r.rayiou == 1.0 and r.rayiou_at == {1.0: 1.0, 2.0: 1.0, 4.0: 1.0}


def _tube_scene(shift: int) -> tuple[OccGrid, np.ndarray, np.ndarray]:
    grid = OccGrid(lower=(0.0, 0.0, 0.0), upper=(0.4 * 60, 0.4, 0.4), voxel_size=0.4)  # 60 x 1 x 1
    gt = np.full(grid.shape, F, np.uint8)
    gt[35] = 15
    pred = np.full(grid.shape, F, np.uint8)
    pred[35 + shift] = 15
    return grid, gt, pred


def test_rayiou_wall_shifted_one_voxel_along_x_by_hand() -> None:
    """Wall scene, derived by hand. The grid is a tube of 60 x 1 x 1 voxels (0.4 m), x in [0, 24],
    y and z in [0, 0.4]; the wall (class 15, manmade) fills the tube's cross-section at voxel
    x = 35 ([14.0, 14.4] m) in the truth and at voxel 36 ([14.4, 14.8] m) in the prediction. One
    origin at (0.2, 0.2, 0.1): 0.2 m from both y sides, 0.1 m above the floor, 0.3 m below the top.

    A ray (azimuth a, pitch p) going forward travels L metres along x with |y| offset L tan a and z
    offset L tan p / cos a; it enters the wall voxel only if both stay inside the tube at the wall's
    near face: truth L = 13.8, prediction L = 14.2.
    - Azimuth: |tan a| < 0.2 / 13.8 = 0.0145 only for a = 0 (tan 1 deg = 0.0175). So a = 0, dy = 0.
    - Pitch (tan p from the list in docs/metrics.md): going up the ray may rise 0.3 m, going down drop 0.1 m.
        tan p = -0.01176: drop 0.162 at 13.8 > 0.1 -> no hit (truth and prediction)
        tan p = -0.00077: drop 0.011 / 0.011 -> truth hit, prediction hit
        tan p = +0.01022: rise 0.141 / 0.145 -> truth hit, prediction hit
        tan p = +0.02121: rise 0.293 < 0.3 at 13.8 -> truth hit; 0.301 > 0.3 at 14.2 -> prediction
                          leaves the grid: no hit (counts as free)
        tan p = +0.03221 or larger, -0.02275 or smaller: no hit.
    - Every other ray misses the truth wall and is dropped.
    So per origin: 3 truth rays of class 15, 2 predicted rays of class 15. For the two rays hit in
    both, both leave the wall through its +x face (rise at 14.6 m is 0.149 < 0.3), so
    |d_pred - d_gt| = 0.4 / cos p = 0.40002 m < 1: a TP at every tau.
    IoU_15 = TP / (gt + pred - TP) = 2 / (3 + 2 - 2) = 2/3 at tau 1, 2, 4; every other class is
    0/0 = NaN, so RayIoU = 2/3.
    Shifted by 3 voxels instead (voxel 38, near face L = 15.0, far face 15.4 m): the same two rays
    hit (rise 0.157 < 0.3, drop 0.012 < 0.1) but |d_pred - d_gt| = 1.2 / cos p = 1.20006:
    not < 1, < 2 -> IoU@1 = 0 / (3 + 2) = 0, IoU@2 = IoU@4 = 2/3, RayIoU = (0 + 2/3 + 2/3) / 3 = 4/9.
    """
    origin = np.array([[0.2, 0.2, 0.1]])
    grid, gt, pred = _tube_scene(1)
    acc = RayIoUAccumulator(grid=grid)
    acc.update(gt, pred, origin)
    r = acc.result()
    assert r.counts[0, 15] == 3 and r.counts[1, 15] == 2 and r.counts[0].sum() == 3
    assert r.per_class[:, 15] == pytest.approx([2 / 3] * 3)
    assert r.rayiou == pytest.approx(2 / 3)
    assert np.isnan(np.delete(r.per_class, 15, axis=1)).all()

    grid, gt, pred = _tube_scene(3)
    acc = RayIoUAccumulator(grid=grid)
    acc.update(gt, pred, origin)
    r = acc.result()
    assert r.per_class[:, 15] == pytest.approx([0.0, 2 / 3, 2 / 3])
    assert r.rayiou == pytest.approx(4 / 9)
    assert r.rayiou_at[1.0] == 0.0


def test_rayiou_accumulator_counts_match_separate_casts_and_merge() -> None:
    """The accumulator (truth and prediction cast in one kernel, prediction skipped where the truth
    hits nothing) counts the same as two `first_hits` casts; merge and state round trip agree."""
    rng = np.random.default_rng(3)
    gt = _random_scene(rng, GRID.shape, 0.01)
    pred = gt.copy()
    flip = rng.random(gt.shape) < 0.002
    pred[flip] = rng.integers(0, 18, flip.sum())
    origins = np.array([[0.94, 0.0, 1.84], [10.0, -5.0, 1.84]])
    acc = RayIoUAccumulator()
    acc.update(gt, pred, origins)
    gd, gc = first_hits(gt, origins)
    pd, pc = first_hits(pred, origins)
    expected = ray_counts(gd, gc, pd, pc)
    np.testing.assert_array_equal(acc.state, expected)
    assert 0 < acc.result().rayiou < 1
    other = RayIoUAccumulator()
    other.update(pred, gt, origins[:1])
    total = expected + other.state
    np.testing.assert_array_equal(RayIoUAccumulator.from_state(acc.state).merge(other).state, total)


def test_ray_counts_threshold_is_strict_in_float32() -> None:
    """|d_pred - d_gt| exactly tau is not a TP; a predicted no-hit (free) never is."""
    gd = np.array([10.0, 10.0, 10.0, 10.0], np.float32)
    gc = np.array([4, 4, 4, F], np.uint8)
    pd = np.array([11.0, 10.5, np.nan, 10.0], np.float32)
    pc = np.array([4, 4, F, 4], np.uint8)
    c = ray_counts(gd, gc, pd, pc)
    assert c[0, 4] == 3 and c[1, 4] == 2 and c[1, F] == 1  # the 4th ray (truth free) is dropped
    assert list(c[2:, 4]) == [1, 2, 2]


@pytest.mark.parametrize("bad", ["pred18", "gt255", "shape"])
def test_rayiou_bad_inputs_raise(bad: str) -> None:
    gt = np.full(GRID.shape, F, np.uint8)
    pred = gt.copy()
    if bad == "pred18":
        pred[0, 0, 0] = 18
    elif bad == "gt255":
        gt[:] = 255
    else:
        pred = pred[:, :, :8]
    with pytest.raises(OccDataError):
        RayIoUAccumulator().update(gt, pred, np.array([[0.94, 0.0, 1.84]]))
