"""OpenOcc v2's mAVE and OccScore (`occdata.eval.flow`): kernels against their numpy twin and a brute-force
march, hand-worked cases, and OpenOcc's own `calc_metrics` run beside ours.

The reference check needs a checkout of OpenDriveLab/OccNet (branch `challenge`; its
`projects/mmdet3d_plugin/datasets/ray_metrics.py` is read at run time, nothing of it is copied here):
`OCCDATA_OPENOCC=/path/to/OccNet pytest tests/test_flow_metrics.py -k reference`.
"""

from __future__ import annotations

import ast
import math
import os
from pathlib import Path

import numpy as np
import pytest
from reference.eval_rayiou import march_reference
from test_metrics import _random_dirs, _random_scene  # the same random scenes as the RayIoU kernel test

from occdata.constants import CLASS_NAMES, FREE_LABEL, GRID, OccGrid
from occdata.eval.flow import MOVING_CLASSES, RayFlowAccumulator, first_hit_voxels, occ_score
from occdata.eval.rayiou import RayIoUAccumulator, first_hits
from occdata.formats.gridspec import GRID_PRESETS
from occdata.formats.occ3d import openocc_to_occ3d

F = FREE_LABEL
CAR, PED, MANMADE = CLASS_NAMES.index("car"), CLASS_NAMES.index("pedestrian"), CLASS_NAMES.index("manmade")
ORIGIN = np.array([[0.94, 0.0, 1.84]])  # a LiDAR origin in key ego


def test_hit_voxel_kernel_equals_numpy_twin_and_first_hits() -> None:
    rng = np.random.default_rng(3)
    small = OccGrid(lower=(-2.0, -2.4, -0.8), upper=(2.8, 2.4, 1.6), voxel_size=0.4)
    for density in (0.02, 0.2):
        lab = _random_scene(rng, small.shape, density)
        origins = np.r_[rng.uniform(small.lower, small.upper, (3, 3)), [[-3.0, 0.1, 0.3]]]  # last: outside
        dirs = _random_dirs(rng, 500)
        d1, c1, k1 = first_hit_voxels(lab, origins, dirs, grid=small)
        d2, c2, k2 = march_reference(lab, origins, dirs, grid=small)
        np.testing.assert_array_equal(k1, k2)
        np.testing.assert_array_equal(c1, c2)
        np.testing.assert_array_equal(d1, d2)
        d3, c3 = first_hits(lab, origins, dirs, grid=small)  # the RayIoU kernel still agrees
        np.testing.assert_array_equal(c1, c3)
        np.testing.assert_array_equal(d1, d3)
        hit = k1 >= 0
        assert hit.any() and (~hit).any()
        np.testing.assert_array_equal(lab.ravel()[k1[hit]], c1[hit])  # the index names the hit voxel
        assert (c1[~hit] == F).all()


def test_hit_voxel_is_where_a_fine_march_first_enters_an_occupied_voxel() -> None:
    """Brute force: step 0.002 m along each ray; the first sample inside an occupied voxel names it."""
    rng = np.random.default_rng(4)
    grid = OccGrid(lower=(-2.0, -2.0, -0.8), upper=(2.0, 2.0, 1.6), voxel_size=0.4)
    lab = _random_scene(rng, grid.shape, 0.08)
    origin = np.array([0.13, -0.21, 0.37])
    lab[tuple(((origin - grid.lower) // 0.4).astype(int))] = F  # the origin's own voxel free
    dirs = _random_dirs(rng, 300)
    _, _, k = first_hit_voxels(lab, origin[None], dirs, grid=grid)
    t = np.arange(0.0, 8.0, 0.002)
    agree = 0
    for r, d in enumerate(dirs.astype(np.float64)):
        p = origin + t[:, None] * d
        v = np.floor((p - grid.lower) / grid.voxel_size).astype(int)
        inside = np.all((v >= 0) & (v < grid.shape), axis=1)
        v = v[: np.argmin(inside) if not inside.all() else len(v)]  # until the ray leaves the grid
        occ = lab[tuple(v.T)] != F
        brute = int(np.ravel_multi_index(tuple(v[np.argmax(occ)]), grid.shape)) if occ.any() else -1
        agree += brute == k[0, r]
    assert agree >= 0.99 * len(dirs)  # a ray grazing a voxel edge may differ from a 2 mm march


def _wall_scene(x_gt: int, x_pred: int, cls: int) -> tuple[np.ndarray, np.ndarray]:
    """A wall of `cls` filling the plane x = x_gt (truth) / x_pred (prediction), every y and z."""
    gt = np.full(GRID.shape, F, np.uint8)
    pred = gt.copy()
    gt[x_gt] = cls
    pred[x_pred] = cls
    return gt, pred


def test_hand_worked_ave_mave_and_occ_score() -> None:
    """Identical car walls, truth flow (2, 0), predicted (2.75, -1): every TP ray errs by exactly 1.25 m/s.
    RayIoU = 1 (same grids) -> OccScore = 0.9 + 0.1 max(1 - 1.25, 0) = 0.9. Adding a pedestrian wall with
    an exact flow makes mAVE (1.25 + 0) / 2 = 0.625 and OccScore 0.9 + 0.1 x 0.375 = 0.9375."""
    gt, pred = _wall_scene(130, 130, CAR)
    fg = np.zeros((*GRID.shape, 2), np.float32)
    fp = fg.copy()
    fg[130] = (2.0, 0.0)
    fp[130] = (2.75, -1.0)
    acc = RayFlowAccumulator()
    acc.update(gt, pred, ORIGIN, fg, fp)
    r = acc.result()
    assert r.rayiou == 1.0 and r.ave_per_class[CAR] == 1.25 and r.mave == 1.25
    assert r.occ_score == pytest.approx(0.9, abs=1e-15)
    assert all(math.isnan(r.ave_per_class[c]) for c in range(17) if c != CAR)  # no TP ray: NaN, skipped
    gt[60] = PED
    pred[60] = PED
    fg[60] = fp[60] = (-1.5, 0.5)
    acc = RayFlowAccumulator()
    acc.update(gt, pred, ORIGIN, fg, fp)
    r = acc.result()
    assert r.ave_per_class[PED] == 0.0 and r.mave == 0.625 and r.occ_score == pytest.approx(0.9375, abs=1e-15)


def test_each_flow_is_read_at_its_own_grids_first_hit() -> None:
    """Truth wall at x = 130, predicted one voxel (0.4 m) further, at 131: rays within 2 m are TPs. Each
    grid's flow is right only at its own wall (the other layer holds a wrong value), so sampling the
    prediction at the truth's voxel (or the reverse) would show an error; the right reading shows 0."""
    gt, pred = _wall_scene(130, 131, CAR)
    fg = np.zeros((*GRID.shape, 2), np.float32)
    fp = fg.copy()
    fg[130], fg[131] = (3.0, 1.0), (7.0, 7.0)
    fp[131], fp[130] = (3.0, 1.0), (-5.0, 0.0)
    acc = RayFlowAccumulator()
    acc.update(gt, pred, ORIGIN, fg, fp)
    r = acc.result()
    assert acc.flow_state[1, CAR] > 1000  # many TP rays
    assert r.ave_per_class[CAR] == 0.0 and r.mave == 0.0
    assert 0 < r.rayiou < 1  # oblique rays miss the 2 m (and 1 m) windows: not all rays are TPs


def test_no_moving_tp_gives_nan_and_flowless_path_is_rayiou() -> None:
    gt, pred = _wall_scene(130, 130, MANMADE)
    flow = np.ones((*GRID.shape, 2), np.float32)
    acc = RayFlowAccumulator()
    acc.update(gt, pred, ORIGIN, flow, flow * 0)
    r = acc.result()
    assert math.isnan(r.mave) and math.isnan(r.occ_score) and r.rayiou == 1.0
    assert math.isnan(occ_score(0.5, float("nan"))) and occ_score(0.5, 3.0) == pytest.approx(0.45)
    # RayIoU counts are the same whichever accumulator casts them, with or without flow
    rng = np.random.default_rng(5)
    g, p = _random_scene(rng, GRID.shape, 0.01), _random_scene(rng, GRID.shape, 0.01)
    plain, flowed, no_flow = RayIoUAccumulator(), RayFlowAccumulator(), RayFlowAccumulator()
    plain.update(g, p, ORIGIN)
    flowed.update(g, p, ORIGIN, flow, flow)
    no_flow.update(g, p, ORIGIN)
    np.testing.assert_array_equal(plain.state, flowed.state)
    np.testing.assert_array_equal(plain.state, no_flow.state)
    merged = RayFlowAccumulator.from_states(flowed.state, flowed.flow_state).merge(flowed)
    np.testing.assert_array_equal(merged.flow_state, 2 * flowed.flow_state)


# --- OpenOcc's own calc_metrics beside ours -----------------------------------------------------------------
def _openocc_calc_metrics():  # noqa: ANN202
    root = os.environ.get("OCCDATA_OPENOCC")
    if not root:
        pytest.skip("set OCCDATA_OPENOCC to an OpenDriveLab/OccNet checkout (branch challenge) to run the reference")
    src = (Path(root) / "projects" / "mmdet3d_plugin" / "datasets" / "ray_metrics.py").read_text()
    ns: dict = {"np": np}
    for node in ast.parse(src).body:  # its module imports torch and compiles a CUDA extension: take the parts
        keep = isinstance(node, ast.FunctionDef) and node.name == "calc_metrics"
        keep |= isinstance(node, ast.Assign) and any(getattr(t, "id", "") in ("occ_class_names", "flow_class_names")
                                                     for t in node.targets)
        if keep:
            exec(compile(ast.Module([node], []), "openocc_ray_metrics", "exec"), ns)  # noqa: S102
    return ns["calc_metrics"], ns["occ_class_names"]


def _openocc_scene(rng: np.random.Generator) -> np.ndarray:
    """Boxes of OpenOcc v2 classes (0..15) in free space (16), in OpenOcc ids."""
    sem = np.full(GRID.shape, 16, np.uint8)
    sem[:, :, 0] = rng.integers(10, 14, (200, 200))  # a ground layer of flat classes
    for _ in range(120):
        x, y = rng.integers(60, 140, 2)
        z = rng.integers(1, 6)
        a, b, c = rng.integers(1, 7, 3)
        sem[x : x + a, y : y + b, z : z + c] = rng.integers(0, 16)
    return sem


def _pcd(sem_openocc: np.ndarray, flow: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """What the reference's `process_one_sample` makes of a grid: per ray (its label in OpenOcc ids, its
    distance, its flow at its first-hit voxel), from our caster (the one part the reference runs in CUDA)."""
    dist, cls, index = first_hit_voxels(openocc_to_occ3d()[sem_openocc], origins)
    label = np.asarray(GRID_PRESETS["openocc-v2"].class_map, np.uint8)[cls.ravel()]
    f = np.where(index.ravel()[:, None] >= 0, flow.reshape(-1, 2)[np.maximum(index.ravel(), 0)], 0)
    return np.c_[label.astype(np.float32), dist.ravel(), f].astype(np.float32)


def test_mave_and_occ_score_equal_openocc_calc_metrics() -> None:
    calc_metrics, names = _openocc_calc_metrics()
    rng = np.random.default_rng(6)
    to_ours = openocc_to_occ3d()
    acc = RayFlowAccumulator()
    pcd_pred, pcd_gt = [], []
    for _ in range(4):
        gt = _openocc_scene(rng)
        pred = gt.copy()
        pred[np.roll(gt < 16, 1, axis=0) & (rng.random(gt.shape) < 0.5)] = rng.integers(0, 16)  # thicken, relabel
        pred[rng.random(gt.shape) < 0.002] = 16  # holes
        fg = np.where((gt < 8)[..., None], rng.normal(0, 3, (*gt.shape, 2)), 0).astype(np.float32)
        fp = (fg + rng.normal(0, 0.4, fg.shape)).astype(np.float32)
        origins = np.r_[ORIGIN, rng.uniform((-10, -10, 1.5), (10, 10, 2.0), (2, 3))]
        acc.update(to_ours[gt], to_ours[pred], origins, fg, fp)
        g, p = _pcd(gt, fg, origins), _pcd(pred, fp, origins)
        valid = g[:, 0].astype(np.int32) != len(names) - 1  # the reference's `main`: non-free truth rays
        pcd_gt.append(g[valid])
        pcd_pred.append(p[valid])
    with np.errstate(divide="ignore", invalid="ignore"):
        iou_list, ave_list = calc_metrics(pcd_pred, pcd_gt)
    ours = acc.result()
    ids = [CLASS_NAMES.index(n) for n in names[:-1]]  # their 16 classes in ours (no "others")
    np.testing.assert_allclose(ours.per_class[:, ids], np.array(iou_list), rtol=1e-12, equal_nan=True)
    np.testing.assert_allclose(ours.ave_per_class[ids], ave_list, rtol=1e-5, equal_nan=True)  # theirs: float32
    miou, mave = np.nanmean(iou_list), np.nanmean(ave_list)  # the reference's `main`, lines 250-253
    ref_score = miou * 0.9 + max(1 - mave, 0.0) * 0.1
    assert ours.rayiou == pytest.approx(miou, rel=1e-12) and ours.mave == pytest.approx(mave, rel=1e-5)
    assert ours.occ_score == pytest.approx(ref_score, rel=1e-6)
    assert sum(not math.isnan(a) for a in ave_list) >= 6, "most moving classes must have TP rays"
    print(f"\nreference: RayIoU {miou:.6f} mAVE {mave:.6f} OccScore {ref_score:.6f}; ours: {ours.rayiou:.6f} "
          f"{ours.mave:.6f} {ours.occ_score:.6f}; TP rays per moving class {acc.flow_state[1, list(MOVING_CLASSES)]}")
