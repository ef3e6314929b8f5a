"""`occdata view` without a browser: voxel layers, error view, lifted LiDAR points, frustums, the store and
prediction source, the composed frame, the CLI's one-line errors. The browser tests are in
test_view_browser.py."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from occdata.constants import CLASS_NAMES, FREE_LABEL, GRID
from occdata.eval.metrics import confusion_matrix
from occdata.nuscenes.reader import load_lidar_points, load_nuscenes
from occdata.view.config import FrameOptions, ViewConfig
from occdata.view.frame import compose_frame
from occdata.view.source import ViewSource
from occdata.view.voxels import (
    ERROR_KINDS,
    N_SEMANTIC,
    error_ids,
    exposed_voxels,
    frustum_params,
    label_ids,
    layers_from_ids,
    lift_depth_points,
)

REPO = Path(__file__).resolve().parents[1]
FREE = FREE_LABEL


def _brute_exposed(ids: np.ndarray) -> tuple[set, set]:
    """Every voxel with an id, tested face by face in plain Python: (exposed set, top-exposed set)."""
    X, Y, Z = ids.shape
    exposed, top = set(), set()
    for i, j, k in itertools.product(range(X), range(Y), range(Z)):
        if ids[i, j, k] < 0:
            continue
        for d, (di, dj, dk) in enumerate(((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))):
            a, b, c = i + di, j + dj, k + dk
            other = ids[a, b, c] if 0 <= a < X and 0 <= b < Y and 0 <= c < Z else None
            if other is None or other != ids[i, j, k]:
                exposed.add((i, j, k))
                if d == 4:
                    top.add((i, j, k))
    return exposed, top


def test_exposed_voxels_match_a_face_by_face_check_on_random_grids() -> None:
    rng = np.random.default_rng(0)
    for _ in range(5):
        ids = rng.integers(-1, 4, size=(6, 5, 4)).astype(np.int16)
        ijk, node, top = exposed_voxels(ids)
        want, want_top = _brute_exposed(ids)
        got = {tuple(int(v) for v in p) for p in ijk}
        assert got == want
        assert {tuple(int(v) for v in p) for p in ijk[top]} == want_top
        assert np.array_equal(node, ids[tuple(ijk.T)])
        assert np.all(np.diff(node) >= 0)  # grouped by id


def test_a_solid_block_shows_its_shell_only() -> None:
    ids = np.full((5, 5, 5), -1, np.int16)
    ids[1:4, 1:4, 1:4] = 4
    ijk, _, top = exposed_voxels(ids)
    assert len(ijk) == 26 and (2, 2, 2) not in {tuple(p) for p in ijk.tolist()}  # 27 minus the hidden centre
    assert int(top.sum()) == 9  # the 3 x 3 upper layer
    # Per layer: a second class inside the block makes the centre a layer of its own, drawn.
    ids[2, 2, 2] = 7
    ijk, node, _ = exposed_voxels(ids)
    assert len(ijk) == 27 and int((node == 7).sum()) == 1


def test_label_layers_use_class_colours_and_the_mask() -> None:
    lab = np.full(GRID.shape, FREE, np.uint8)
    lab[100, 100, 5] = 4  # car, inside the mask
    lab[10, 10, 2] = 11  # driveable surface, outside
    mask = np.zeros(GRID.shape, np.uint8)
    mask[100, 100, 5] = 1
    layers = {layer.name: layer for layer in layers_from_ids(label_ids(lab, mask))}
    assert set(layers) == {"car", "outside_mask"}
    car = layers["car"]
    assert car.class_id == 4 and car.color == (0, 150, 245) and tuple(car.colors()[0]) == (0, 150, 245)
    # Voxel centre by hand: lower + 0.4 (i + 0.5).
    assert np.allclose(car.centers_ego[0], [-40 + 0.4 * 100.5, -40 + 0.4 * 100.5, -1 + 0.4 * 5.5], atol=1e-5)
    assert layers["outside_mask"].ghost and layers["outside_mask"].class_id is None
    assert {layer.name for layer in layers_from_ids(label_ids(lab))} == {"car", "driveable_surface"}


def test_error_view_counts_agree_with_the_occ3d_confusion_matrix() -> None:
    rng = np.random.default_rng(1)
    gt = np.where(rng.random(GRID.shape) < 0.2, rng.integers(0, 17, GRID.shape), FREE).astype(np.uint8)
    pred = gt.copy()
    flip = rng.random(GRID.shape) < 0.1
    pred[flip] = rng.integers(0, 18, GRID.shape)[flip]
    mask = (rng.random(GRID.shape) < 0.7).astype(np.uint8)
    ids = error_ids(gt, pred, mask)
    cm = confusion_matrix(gt, pred, mask)
    kinds = {kind: int(((ids >= k * N_SEMANTIC) & (ids < (k + 1) * N_SEMANTIC)).sum())
             for k, kind in enumerate(ERROR_KINDS)}
    assert kinds["right"] == int(np.trace(cm[:FREE, :FREE]))
    assert kinds["wrong"] == int(cm[:, :FREE].sum() - np.trace(cm[:FREE, :FREE]))
    assert kinds["missed"] == int(cm[:FREE, FREE].sum())
    outside = ((gt < FREE) | (pred < FREE)) & (mask == 0)
    assert int((ids == 3 * N_SEMANTIC).sum()) == int(outside.sum())


def test_error_layers_name_kind_and_class() -> None:
    gt = np.full(GRID.shape, FREE, np.uint8)
    pred = gt.copy()
    gt[5, 5, 5] = pred[5, 5, 5] = 4  # right car
    gt[9, 9, 5], pred[9, 9, 5] = 11, 4  # wrong: truth road, predicted car -> wrong/driveable_surface
    pred[20, 20, 5] = 4  # wrong: truth free -> wrong/car
    gt[30, 30, 5] = 7  # missed pedestrian
    names = {layer.name: layer for layer in layers_from_ids(error_ids(gt, pred), error_view=True)}
    assert set(names) == {"right/car", "wrong/driveable_surface", "wrong/car", "missed/pedestrian"}
    assert names["wrong/car"].color == names["wrong/driveable_surface"].color != names["right/car"].color


def test_frustums_point_where_the_cameras_look(synth_store: Path) -> None:
    src = ViewSource(synth_store)
    s = src.sample(src.scenes[0], 0)
    K = src.reader.sample_arrays(s.index, ("calib/K",))["calib/K"]
    w, h = src.reader.small("cam/image_size")[s.index, 0]
    assert s.cameras[0].fov_y == pytest.approx(2 * np.arctan(h / 2 / K[0, 1, 1]))
    assert s.cameras[0].aspect == pytest.approx(w / h)
    forward = {}
    for name, cam in zip(s.camera_names, s.cameras, strict=True):
        wq, x, y, z = cam.wxyz  # camera z axis (forward) in key ego, from the quaternion by hand
        forward[name] = np.array([2 * (x * z + wq * y), 2 * (y * z - wq * x), 1 - 2 * (x * x + y * y)])
    assert forward["CAM_FRONT"][0] > 0.95 and forward["CAM_BACK"][0] < -0.95  # ego x forward
    assert forward["CAM_FRONT_LEFT"][1] > 0.5 and forward["CAM_FRONT_RIGHT"][1] < -0.5  # ego y left
    p = frustum_params(np.eye(3) * [100, 100, 1], (200, 100), np.eye(4))
    assert p.fov_y == pytest.approx(2 * np.arctan(0.5)) and p.wxyz == (1.0, 0.0, 0.0, 0.0)


def test_lifted_depth_points_are_the_raw_lidar_points(synth_root: Path, synth_store: Path) -> None:
    """Stored (u, v, depth) lifted through the stored calibration land on the raw keyframe LiDAR
    points (read from the .pcd.bin, moved to ego with the nuScenes tables' calibration)."""
    src = ViewSource(synth_store)
    s = src.sample(src.scenes[0], 1, points=True)
    ds = load_nuscenes(synth_root)
    rec = ds.sample(s.token).lidar
    raw = load_lidar_points(rec.path)[:, :3].astype(np.float64)
    raw_ego = raw @ rec.T_ego_from_lidar[:3, :3].T + rec.T_ego_from_lidar[:3, 3]
    cell = 0.02
    keys = set()
    for off in itertools.product((-1, 0, 1), repeat=3):
        keys.update(map(tuple, (np.floor(raw_ego / cell).astype(np.int64) + off).tolist()))
    lifted = s.points_ego.astype(np.float64)
    assert len(lifted) > 10000
    hit = np.array([tuple(k) in keys for k in np.floor(lifted / cell).astype(np.int64).tolist()])
    assert hit.mean() > 0.999, f"{(~hit).sum()} of {len(hit)} lifted points are not raw LiDAR points"
    # And by hand on one point: project with K and lift back.
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    assert np.allclose(lift_depth_points(np.array([[320 + 500 * 0.5, 240 - 500 * 0.25, 8.0]]), K, T),
                       [[1 + 4.0, 2 - 2.0, 3 + 8.0]], atol=1e-5)


def _write_preds(src: ViewSource, out: Path, change: bool = True) -> dict[str, np.ndarray]:
    preds = {}
    for scene in src.scenes:
        for pos in range(len(scene.indices)):
            s = src.sample(scene, pos)
            pred = s.semantics.copy()
            if change:
                pred[pred == 4] = 10  # cars predicted as trucks: wrong
                pred[pred == 7] = FREE  # pedestrians missed
            d = out / scene.name / s.token
            d.mkdir(parents=True)
            np.savez_compressed(d / "labels.npz", semantics=pred)
            preds[s.token] = pred
    return preds


def test_source_lists_scenes_splits_and_reads_predictions(synth_store: Path, tmp_path: Path) -> None:
    src = ViewSource(synth_store)
    assert [(s.name, s.split, len(s.indices)) for s in src.scenes] == [("synth-0000", "train", 3),
                                                                      ("synth-0001", "val", 3)]
    assert [s.name for s in ViewSource(synth_store, split="val").scenes] == ["synth-0001"]
    preds = _write_preds(src, tmp_path / "pred")
    with_pred = ViewSource(synth_store, pred=tmp_path / "pred")
    s = with_pred.sample(with_pred.scenes[1], 2, images=True)
    assert np.array_equal(s.pred, preds[s.token]) and s.position == 2 and s.n_in_scene == 3
    assert len(s.images) == 6 and s.images[0].dtype == np.uint8 and s.images[0].shape[2] == 3
    assert set(s.masks) >= {"camera", "lidar"}
    frame = compose_frame(s, FrameOptions(view="error", mask="camera"))
    names = {layer.name for g in frame.groups for layer in g.layers}
    assert "wrong/car" in names and "missed/pedestrian" in names and "outside_mask" in names
    side = compose_frame(s, FrameOptions(view="side"))
    assert [(g.name, g.offset[1]) for g in side.groups] == [("truth", 44.0), ("pred", -44.0)]


def test_empty_split_and_missing_labels_are_said_in_words(synth_root: Path, synth_store: Path,
                                                          tmp_path: Path) -> None:
    from occdata.store.build import BuildConfig, build_store

    empty = ViewSource(synth_store, split="test")
    assert not empty.scenes and "split 'test' has no built samples" in empty.empty_reason()
    out = tmp_path / "nolabels.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=None, progress=False))
    src = ViewSource(out)
    s = src.sample(src.scenes[0], 0)
    assert s.semantics is None and not src.has_labels()
    frame = compose_frame(s, FrameOptions())
    assert not frame.groups and "No labels for this sample" in frame.notes[0]


def test_view_config_validates_and_knows_when_it_is_exposed() -> None:
    assert not ViewConfig(store="x").exposed and not ViewConfig(store="x", host="localhost").exposed
    assert ViewConfig(store="x", host="0.0.0.0").exposed and ViewConfig(store="x", host="192.168.1.4").exposed
    from occdata.errors import OccDataError

    with pytest.raises(OccDataError, match="needs --pred"):
        ViewConfig(store="x", frame=FrameOptions(view="error"))
    with pytest.raises(OccDataError, match="unknown mask"):
        FrameOptions(mask="radar")


def _cli(*args: str, prelude: str = "") -> subprocess.CompletedProcess:
    code = f"{prelude}import sys; from cli.occdata_cli import main; sys.argv = ['occdata'] + sys.argv[1:]; main()"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=REPO, env=env,
                          timeout=120)


def test_missing_viser_is_one_line_naming_the_extra(synth_store: Path) -> None:
    r = _cli("view", "--store", str(synth_store), "--port", "0", prelude="import sys; sys.modules['viser'] = None; ")
    assert r.returncode == 1
    assert r.stderr.strip().count("\n") == 0 and "pip install 'fastocc[view]'" in r.stderr, r.stderr
    assert "pip install -e '.[view]'" in r.stderr, r.stderr  # the form for a clone


def test_unknown_scene_is_one_line(synth_store: Path) -> None:
    r = _cli("view", "--store", str(synth_store), "--scene", "nowhere", "--port", "0")
    assert r.returncode == 1 and "scene 'nowhere'" in r.stderr and "Traceback" not in r.stderr


def test_view_package_never_imports_torch() -> None:
    code = ("import sys; import occdata.view.run, occdata.view.app, occdata.view.draw; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120)
    assert r.returncode == 0, r.stderr


def test_class_names_cover_the_layers() -> None:
    assert len(CLASS_NAMES) == N_SEMANTIC + 1
