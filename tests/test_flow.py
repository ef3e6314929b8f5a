"""Occupancy flow: the devkit's box velocity, which box a voxel takes it from, and its fidelity.

Independent truth: hand-computed velocities, the official devkit's `NuScenes.box_velocity` (run in the
devkit venv, OCCDATA_DEVKIT_PYTHON), the real scene-0916's boxes (containment computed here, not by the
generator), and the synthetic world's actor motion (`occdata.synth`: constant speed along the road path,
differentiated numerically at the keyframe time).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_SEQ, missing_fixture

from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.formats.gridspec import GRID_PRESETS
from occdata.geometry import invert_rigid, points_in_box, transform_points
from occdata.labels.boxes import box_class, held_static
from occdata.labels.flow import voxel_flow
from occdata.labels.kernels import majority, vote_sources
from occdata.labels.options import LabelOptions
from occdata.labels.scene import label_scene
from occdata.nuscenes.annotations import Annotations, BoxRecord, box_velocity, load_annotations

needs_devkit = pytest.mark.skipif(
    not os.environ.get("OCCDATA_DEVKIT_PYTHON"),
    reason="set OCCDATA_DEVKIT_PYTHON to a python with nuscenes-devkit (scripts/devkit_env.sh)",
)
N_CLS = NUM_CLASSES - 1


def _box(tok: str, x: float, t_s: float, prev: str = "", next_: str = "", y: float = 0.0) -> BoxRecord:
    return BoxRecord(tok, "inst", "s", "vehicle.car", np.array([x, y, 1.0]), np.array([2.0, 4.0, 1.5]),
                     np.array([1.0, 0, 0, 0]), int(round(t_s * 1e6)), 10, prev, next_)


# --- box_velocity: hand values ------------------------------------------------------------------------
def test_box_velocity_hand_values() -> None:
    a, b, c = _box("a", 0.0, 0.0), _box("b", 3.0, 0.5, y=1.0), _box("c", 10.0, 1.0, y=2.0)
    np.testing.assert_allclose(box_velocity(b, a, c), [10.0, 2.0, 0.0])  # centred: (c - a) / 1 s
    np.testing.assert_allclose(box_velocity(a, None, b), [6.0, 2.0, 0.0])  # one-sided at the start
    np.testing.assert_allclose(box_velocity(c, b, None), [14.0, 2.0, 0.0])  # ... and at the end
    assert np.isnan(box_velocity(a, None, None)).all()  # no neighbour
    far = _box("f", 16.0, 2.0)
    assert np.isnan(box_velocity(a, None, far)).all()  # one-sided over 2 s > 1.5 s
    np.testing.assert_allclose(box_velocity(b, a, far), [8.0, 0.0, 0.0])  # centred over 2 s <= 3 s
    assert np.isnan(box_velocity(b, a, _box("g", 0.0, 3.5))).all()  # centred over 3.5 s > 3 s
    np.testing.assert_allclose(box_velocity(a, None, _box("h", 1.5, 1.5)), [1.0, 0.0, 0.0])  # 1.5 s: kept


def test_annotations_follow_prev_next_links() -> None:
    a, b, c = _box("a", 0.0, 0.0, next_="b"), _box("b", 3.0, 0.5, "a", "c"), _box("c", 10.0, 1.0, "b")
    v = Annotations({"s0": (a,), "s1": (b,), "s2": (c,)}, {"inst": "vehicle.car"}).box_velocities()
    np.testing.assert_allclose(v["a"], [6.0, 0, 0])
    np.testing.assert_allclose(v["b"], [10.0, 0, 0])
    np.testing.assert_allclose(v["c"], [14.0, 0, 0])


DEVKIT_VELOCITY = r'''
import json, sys
from nuscenes import NuScenes
nusc = NuScenes(version="v1.0-mini", dataroot=sys.argv[1], verbose=False)
out = {a["token"]: [None if v != v else float(v) for v in nusc.box_velocity(a["token"])]
       for a in nusc.sample_annotation}
json.dump(out, open(sys.argv[2], "w"))
'''


@pytest.fixture(scope="module")
def seq_root() -> Path:
    if not (REAL_SEQ / "v1.0-mini" / "sample_annotation.json").is_file():
        missing_fixture("real nuScenes scene", REAL_SEQ)
    return REAL_SEQ


@needs_devkit
def test_box_velocity_matches_devkit_on_real_scene(seq_root: Path, tmp_path: Path) -> None:
    res = subprocess.run([os.environ["OCCDATA_DEVKIT_PYTHON"], "-c", DEVKIT_VELOCITY, str(seq_root),
                          str(tmp_path / "v.json")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    devkit = json.loads((tmp_path / "v.json").read_text())
    ours = load_annotations(seq_root, "v1.0-mini").box_velocities()
    assert set(ours) == set(devkit) and len(ours) == 2424
    want = np.array([[np.nan if v is None else v for v in devkit[t]] for t in sorted(devkit)])
    got = np.array([ours[t] for t in sorted(devkit)])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=0, atol=1e-12)
    assert np.isnan(want[:, 0]).sum() < len(want)  # the scene has usable velocities


# --- which box a voxel's flow comes from --------------------------------------------------------------
def _keys(voxel_class: list[tuple[int, int]]) -> np.ndarray:
    return np.array([v * N_CLS + c for v, c in voxel_class], np.int64)


def test_vote_sources_most_votes_of_the_winning_class() -> None:
    shape = (2, 2, 2)
    static = _keys([(0, 15), (0, 15), (1, 4), (2, 11), (3, 4)])
    box_a = _keys([(1, 4), (1, 4), (2, 4), (3, 4)])  # voxel 1: 2 car votes vs static's 1
    box_b = _keys([(1, 4), (1, 7), (1, 7), (2, 4), (3, 4), (3, 4)])  # voxel 2: tie with box a; voxel 3: most
    votes = [static, box_a, box_b]
    sem = majority(votes, shape, N_CLS, FREE_LABEL)
    assert sem.reshape(-1)[:4].tolist() == [15, 4, 4, 4]  # voxel 1: car 3 votes vs pedestrian 2
    voxel, source = vote_sources(votes, sem, N_CLS)
    # voxel 0: no box votes, not returned; 1: box a (2 car votes; box b's pedestrians do not count);
    # 2: boxes a and b tie with 1 car vote each, the lower wins; 3: box b's 2 against 1 and 1.
    assert dict(zip(voxel.tolist(), source.tolist(), strict=True)) == {1: 1, 2: 1, 3: 2}
    tie_static = [_keys([(5, 4)]), _keys([(5, 4)])]
    sem = majority(tie_static, shape, N_CLS, FREE_LABEL)
    assert vote_sources(tie_static, sem, N_CLS)[1].tolist() == [0]  # the static scene wins a tie


def test_flow_rotates_the_ground_velocity_into_the_grid() -> None:
    shape = (2, 2, 2)
    votes = [_keys([(0, 15)]), _keys([(1, 4)]), _keys([(2, 4)])]
    sem = majority(votes, shape, N_CLS, FREE_LABEL)
    yaw = np.pi / 2  # grid x = global y
    R_grid_from_global = np.array([[np.cos(yaw), np.sin(yaw), 0], [-np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    v_global = np.array([[9.0, 9.0, 9.0], [3.0, 1.0, 5.0], [0.0, -2.0, 0.0]])  # box 0 has no points here
    flow = voxel_flow(votes, [1, 2], sem, v_global, R_grid_from_global)
    assert flow.shape == (2, 2, 2, 2) and flow.dtype == np.float32
    f = flow.reshape(-1, 2)
    np.testing.assert_allclose(f[1], [1.0, -3.0], atol=1e-6)
    np.testing.assert_allclose(f[2], [-2.0, 0.0], atol=1e-6)
    assert not f[[0, *range(3, 8)]].any()


# --- real scene-0916: each object voxel's flow is the velocity of the box that holds it ----------------
@pytest.fixture(scope="module")
def real_flow(seq_root: Path, tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    """scene-0916 labelled on the occ3d grid (no flow) and the openocc-v2 grid (the same grid, with flow)
    in one run, which voxelises them once, and on the occ3d grid alone; keyframes only (the tree ships
    no sweep files)."""
    from occdata.labels.generate import LabelsConfig, load_inputs

    inputs, _ = load_inputs(LabelsConfig(root=seq_root, out=tmp_path_factory.mktemp("o"), progress=False))
    scene = inputs.dataset.scenes[0]
    scene_inputs = inputs.for_scene(scene)
    grids = (GRID_PRESETS["occ3d"], GRID_PRESETS["openocc-v2"])
    labels, _ = label_scene(scene_inputs, scene, LabelOptions(), grids=grids, flow=("openocc-v2",))
    alone, _ = label_scene(scene_inputs, scene, LabelOptions(), grids=grids[:1])
    return scene_inputs, labels["openocc-v2"], labels["occ3d"], alone["occ3d"]


@pytest.mark.slow
def test_flow_is_per_grid_and_changes_nothing_else(real_flow) -> None:  # noqa: ANN001
    _, with_flow, without, alone = real_flow
    assert set(with_flow) == set(without) == set(alone) and len(without) == 41
    for tok, labels in alone.items():
        assert "flow" not in labels and "flow" not in without[tok] and list(with_flow[tok]) == [*labels, "flow"]
        for key, arr in labels.items():  # the shared run equals a run of the occ3d grid alone, without flow
            assert arr.tobytes() == with_flow[tok][key].tobytes() == without[tok][key].tobytes()
        assert with_flow[tok]["flow"].shape == (200, 200, 16, 2) and with_flow[tok]["flow"].dtype == np.float32


def _voxel_centres(spec_grid, idx: np.ndarray) -> np.ndarray:  # noqa: ANN001
    return np.asarray(spec_grid.lower) + (idx + 0.5) * spec_grid.voxel_size


def real_flow_check(inputs, labels: dict) -> dict[str, int]:  # noqa: ANN001
    """Counts over the scene's keyframes, for object voxels (classes 1-10; the scene has no lidarseg, so
    its static points are class 0, as are boxes of "others" categories: class 0 enters the flowing
    count only): those held by exactly one box of their class (the
    box grown by the generator's 0.1 m margin and half a voxel diagonal; boxes of the keyframe, and the
    parked boxes drawn where annotation stopped, velocity 0), those of them whose flow equals that box's
    velocity rotated into key ego, and flowing voxels whose flow is no holding box's velocity."""
    grid = GRID_PRESETS["occ3d"].grid
    vel = inputs.annotations.box_velocities()
    reach = 0.1 + np.sqrt(3) * grid.voxel_size / 2
    keyframe_boxes = [inputs.annotations.boxes_by_sample.get(s.token, ()) for s in inputs.dataset.samples]
    held = held_static(keyframe_boxes, LabelOptions().hold_static)
    n = {"held_by_one": 0, "equal": 0, "flowing": 0, "flowing_unexplained": 0}
    for s, annotated, parked in zip(inputs.dataset.samples, keyframe_boxes, held, strict=True):
        sem, flow = labels[s.token]["semantics"], labels[s.token]["flow"]
        idx = np.argwhere(((sem >= 1) & (sem <= 10)) | flow.any(axis=-1))
        cls = sem[tuple(idx.T)]
        R_keyego_from_global = invert_rigid(s.T_global_from_keyego)[:3, :3]
        centres_global = transform_points(s.T_global_from_keyego, _voxel_centres(grid, idx))
        boxes = annotated + parked
        inside = np.zeros((len(idx), len(boxes)), bool)
        v_grid = np.zeros((len(boxes), 2))
        for b, box in enumerate(boxes):
            half = np.array([box.size_wlh[1] / 2, box.size_wlh[0] / 2, box.size_wlh[2] / 2]) + reach
            inside[:, b] = points_in_box(centres_global, invert_rigid(box.T_global_from_box()), half)
            inside[:, b] &= cls == box_class(box)
            if b < len(annotated):
                v_grid[b] = (R_keyego_from_global @ np.nan_to_num(vel[box.token] * (1, 1, 0)))[:2]
        f = flow[tuple(idx.T)].astype(np.float64)
        one = (inside.sum(axis=1) == 1) & (cls >= 1)
        n["held_by_one"] += int(one.sum())
        own = v_grid[np.argmax(inside[one], axis=1)]
        n["equal"] += int(np.all(np.abs(f[one] - own) < 1e-4, axis=1).sum())
        moving = np.abs(f).max(axis=1) > 0
        explained = np.zeros(len(f), bool)
        for b in range(len(boxes)):
            explained |= inside[:, b] & np.all(np.abs(f - v_grid[b]) < 1e-4, axis=1)
        n["flowing"] += int(moving.sum())
        n["flowing_unexplained"] += int((moving & ~explained).sum())
        assert not flow[sem > 10].any(), "free and stuff (ground, manmade, vegetation) voxels have no flow"
    return n


@pytest.mark.slow
def test_real_scene_flow_is_the_holding_box_velocity(real_flow) -> None:  # noqa: ANN001
    inputs, with_flow, _, _ = real_flow
    n = real_flow_check(inputs, with_flow)
    print(f"\nscene-0916 flow: {n}  equal share {n['equal'] / max(n['held_by_one'], 1):.4f}")
    assert n["flowing"] > 100, "the scene must have moving objects for this test to mean anything"
    assert n["flowing_unexplained"] == 0
    assert n["equal"] / n["held_by_one"] >= 0.99


# --- synthetic world: flow against the actors' true velocity --------------------------------------------
SYNTH = {"scenes": 1, "samples": 6, "seed": 11, "width": 320, "height": 180}  # as tests/test_labels.py
BOX_KIND_CLASSES = (1, 2, 3, 4, 6, 7, 8, 10)  # barrier .. truck: the synthetic world's box kinds


def synthetic_flow_errors(world_root: Path, labels: dict, samples) -> dict[str, np.ndarray]:  # noqa: ANN001
    """Per correctly occupied object voxel (generated class = truth class, a box kind) that lies in exactly
    one object's box (grown by half a voxel diagonal): `error` |flow - true velocity| (m/s, key ego) and
    `moving` (the object moves), `speed` its true speed. The truth is the world's exact actor motion at the
    keyframe time."""
    from occdata.synth.annotations import object_boxes, object_velocities
    from occdata.synth.pipeline import ego_transform, scene_world

    world = scene_world(SYNTH["seed"], 0, SYNTH["samples"])
    grid = GRID_PRESETS["occ3d"].grid
    reach = np.sqrt(3) * grid.voxel_size / 2
    err, moving, speed = [], [], []
    for s in samples:
        truth = np.load(world_root / "gts" / s.scene_name / s.token / "labels.npz")["semantics"]
        sem, flow = labels[s.token]["semantics"], labels[s.token]["flow"]
        idx = np.argwhere((sem == truth) & np.isin(sem, BOX_KIND_CLASSES))
        T_global_from_keyego = ego_transform(world, s.timestamp)
        boxes = object_boxes(world, s.timestamp)
        v_keyego = object_velocities(world, s.timestamp) @ invert_rigid(T_global_from_keyego)[:3, :3].T
        centres_global = transform_points(T_global_from_keyego, _voxel_centres(grid, idx))
        inside = np.zeros((len(idx), len(boxes)), bool)
        for b in range(len(boxes)):
            c, si = np.cos(boxes.yaw[b]), np.sin(boxes.yaw[b])
            T_global_from_box = np.array([[c, -si, 0, boxes.center[b, 0]], [si, c, 0, boxes.center[b, 1]],
                                          [0, 0, 1, boxes.center[b, 2]], [0, 0, 0, 1]])
            w, length, h = boxes.size_wlh[b]
            half = np.array([length / 2, w / 2, h / 2]) + reach
            inside[:, b] = points_in_box(centres_global, invert_rigid(T_global_from_box), half)
        one = inside.sum(axis=1) == 1
        owner = np.argmax(inside[one], axis=1)
        f = flow[tuple(idx[one].T)].astype(np.float64)
        err.append(np.linalg.norm(f - v_keyego[owner, :2], axis=1))
        moving.append(boxes.speed[owner] > 0)
        speed.append(np.linalg.norm(v_keyego[owner, :2], axis=1))
    return {"error": np.concatenate(err), "moving": np.concatenate(moving), "speed": np.concatenate(speed)}


@pytest.fixture(scope="module")
def synth_flow(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    from occdata.labels.generate import LabelsConfig, load_inputs
    from occdata.synth import SynthConfig, synthesize

    root = synthesize(SynthConfig(out=tmp_path_factory.mktemp("flow") / "world", progress=False, **SYNTH))
    opts = LabelOptions(all_sweeps=True)
    inputs, _ = load_inputs(LabelsConfig(root=root, out=tmp_path_factory.mktemp("o"), options=opts, progress=False))
    scene = inputs.dataset.scenes[0]
    labels, _ = label_scene(inputs.for_scene(scene), scene, opts, flow=True)
    return root, labels["occ3d"], inputs.dataset.samples


@pytest.mark.slow
def test_synthetic_flow_error_is_small(synth_flow) -> None:  # noqa: ANN001
    root, labels, samples = synth_flow
    e = synthetic_flow_errors(root, labels, samples)
    err, moving = e["error"], e["moving"]
    print(f"\nsynthetic flow error (m/s) over {len(err)} correct object voxels: median {np.median(err):.2e} "
          f"p90 {np.percentile(err, 90):.2e} max {err.max():.2e}; moving ({moving.sum()} voxels, true speed "
          f"{np.percentile(e['speed'][moving], [0, 50, 100]).round(2).tolist()} m/s): median "
          f"{np.median(err[moving]):.2e} p90 {np.percentile(err[moving], 90):.2e} max {err[moving].max():.2e}")
    assert moving.sum() > 100, "the world must have moving objects for this test to mean anything"
    assert np.median(err) < 0.1
    assert np.median(err[moving]) < 0.1


def test_box_velocity_against_synthetic_truth_on_curves() -> None:
    """The devkit's centre difference over +-0.5 s against the actors' instantaneous velocity, over every
    actor box of three 40-keyframe synthetic scenes (their roads curve; boxes only, nothing rendered)."""
    from occdata.synth.annotations import object_boxes, object_velocities
    from occdata.synth.pipeline import keyframe_times, scene_world

    err, speed, centred = [], [], []
    for seed in (1, 2, 3):
        world = scene_world(seed, 0, 40)
        tracks: dict[str, list[tuple[BoxRecord, np.ndarray]]] = {}
        for k, t_us in enumerate(keyframe_times(0, 40)):
            boxes, v_true = object_boxes(world, t_us), object_velocities(world, t_us)
            for b, key in enumerate(boxes.keys):
                if key.startswith("actor"):
                    rec = _box(f"{key}-{k}", 0.0, t_us * 1e-6)
                    tracks.setdefault(key, []).append((replace_center(rec, boxes.center[b]), v_true[b]))
        for items in tracks.values():
            for n, (box, v) in enumerate(items):
                prev = items[n - 1][0] if n > 0 else None
                next_ = items[n + 1][0] if n + 1 < len(items) else None
                err.append(np.linalg.norm(box_velocity(box, prev, next_)[:2] - v[:2]))
                speed.append(np.linalg.norm(v[:2]))
                centred.append(prev is not None and next_ is not None)
    err_a, c = np.array(err), np.array(centred)
    print(f"\nbox velocity vs synthetic truth, {len(err_a)} actor boxes ({c.sum()} centred) at "
          f"{np.percentile(speed, [50, 100]).round(1).tolist()} m/s (median, max): error median "
          f"{np.median(err_a):.4f} p90 {np.percentile(err_a, 90):.4f} max {err_a.max():.4f} m/s; centred: median "
          f"{np.median(err_a[c]):.4f} p90 {np.percentile(err_a[c], 90):.4f} max {err_a[c].max():.4f}; one-sided: "
          f"median {np.median(err_a[~c]):.4f} max {err_a[~c].max():.4f}")
    assert len(err_a) > 100 and c.sum() > 100
    assert np.median(err_a) < 0.1 and np.percentile(err_a[c], 90) < 0.1


def replace_center(box: BoxRecord, center_global: np.ndarray) -> BoxRecord:
    from dataclasses import replace

    return replace(box, center_global=np.asarray(center_global, np.float64))


def test_vote_sources_agrees_with_brute_force() -> None:
    """Random votes of a static scene and 6 boxes on a 4x4x3 grid against a per-voxel count in Python."""
    rng = np.random.default_rng(0)
    shape, n_vox = (4, 4, 3), 48
    votes = [np.sort(rng.integers(0, n_vox, 300)) * N_CLS + rng.choice([4, 11, 15], 300)]
    votes += [rng.integers(0, n_vox // 2, rng.integers(1, 40)) * N_CLS + rng.choice([4, 7], 1) for _ in range(6)]
    votes = [v.astype(np.int64) for v in votes]
    sem = majority(votes, shape, N_CLS, FREE_LABEL).reshape(-1)
    voxel, source = vote_sources(votes, sem.reshape(shape), N_CLS)
    want = {}
    for v in range(n_vox):
        counts = [int(np.sum(keys == v * N_CLS + int(sem[v]))) for keys in votes]
        if any(np.any(keys // N_CLS == v) for keys in votes[1:]):
            want[v] = int(np.argmax(counts))  # argmax: the first, i.e. the lowest source, on a tie
    assert dict(zip(voxel.tolist(), source.tolist(), strict=True)) == want
    assert len(want) > 10 and any(s > 0 for s in want.values()) and any(s == 0 for s in want.values())
