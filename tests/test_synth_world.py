"""The synthetic world is geometrically exact: LiDAR, depth maps, labels and masks agree through the tables."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from occdata.constants import CAMERA_ORDER, FREE_LABEL, GRID
from occdata.geometry import transform_points
from occdata.nuscenes import load_lidar_points, load_nuscenes
from occdata.synth.rig import CAMERA_TIME_OFFSETS_US, RIG
from occdata.visibility import GROUND_CLASSES


@pytest.fixture(scope="module")
def ds(synth_root: Path):
    return load_nuscenes(synth_root, version="v1.0-mini")


def _depth_of(root: Path, token: str) -> np.ndarray:
    return np.load(root / "depth" / f"{token}.npy")


def _labels(root: Path, sample) -> dict[str, np.ndarray]:
    with np.load(root / "gts" / sample.scene_name / sample.token / "labels.npz") as z:
        return {k: z[k] for k in z.files}


def _bilinear_inverse_depth(depth: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth at sub-pixel `uv (N, 2)` by bilinear interpolation of 1/depth (exact on planes), and a flag
    that the 3x3 neighbourhood is smooth (no depth edge, no sky)."""
    H, W = depth.shape
    u0 = np.floor(uv[:, 0]).astype(int)
    v0 = np.floor(uv[:, 1]).astype(int)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-9), 0.0)
    i00, i01 = inv[v0, u0], inv[v0, u0 + 1]
    i10, i11 = inv[v0 + 1, u0], inv[v0 + 1, u0 + 1]
    interp = (1 - fv) * ((1 - fu) * i00 + fu * i01) + fv * ((1 - fu) * i10 + fu * i11)
    patch = np.stack([depth[np.clip(v0 + dv, 0, H - 1), np.clip(u0 + du, 0, W - 1)]
                      for dv in (-1, 0, 1, 2) for du in (-1, 0, 1, 2)], 1)
    smooth = (patch.min(axis=1) > 0) & (patch.max(axis=1) < 1.02 * patch.min(axis=1))
    return 1.0 / np.maximum(interp, 1e-12), smooth


def _depth_errors(ds, root: Path) -> np.ndarray:
    """|rendered depth - LiDAR point depth| for points projected through the stored tables (devkit chain
    lidar -> ego(t_lidar) -> global -> ego(t_cam) -> camera -> K), away from depth edges."""
    errors = []
    for sample in ds.samples:
        pts = load_lidar_points(sample.lidar.path)
        assert pts.shape[1] == 5 and pts.dtype == np.float32
        for i, cam in enumerate(sample.cameras):
            p_cam = transform_points(sample.T_cam_from_lidar(i), pts[:, :3])
            z = p_cam[:, 2]
            keep = z > 1.0
            uv = p_cam[keep, :2] / z[keep, None] @ cam.K[:2, :2].T + cam.K[:2, 2]
            inside = (uv[:, 0] > 1) & (uv[:, 0] < cam.width - 2) & (uv[:, 1] > 1) & (uv[:, 1] < cam.height - 2)
            depth = _depth_of(root, cam.token)
            assert depth.shape == (cam.height, cam.width) and depth.dtype == np.float32
            d_img, smooth = _bilinear_inverse_depth(depth, uv[inside])
            errors.append(np.abs(d_img - z[keep][inside])[smooth])
    return np.concatenate(errors)


def _occupied_fraction(ds, root: Path) -> tuple[float, int]:
    """Fraction of in-grid LiDAR returns (key ego) that fall in occupied voxels; also checks mask_lidar."""
    inside_total = occupied_total = 0
    for sample in ds.samples:
        pts = load_lidar_points(sample.lidar.path)
        p_keyego = transform_points(sample.lidar.T_ego_from_lidar, pts[:, :3])
        idx = GRID.index_of(p_keyego)
        ok = ((idx >= 0) & (idx < np.array(GRID.shape))).all(axis=1)
        lab = _labels(root, sample)
        labels = lab["semantics"][idx[ok, 0], idx[ok, 1], idx[ok, 2]]
        inside_total += int(ok.sum())
        occupied_total += int((labels != FREE_LABEL).sum())
        # The LiDAR mask covers every voxel a return ends in.
        assert lab["mask_lidar"][idx[ok, 0], idx[ok, 1], idx[ok, 2]].all()
    return occupied_total / inside_total, inside_total


def test_lidar_projects_onto_rendered_depth(ds, synth_root: Path) -> None:
    err = _depth_errors(ds, synth_root)
    print(f"\nLiDAR vs rendered depth: {len(err)} points away from edges, median |err| = {np.median(err) * 100:.2f} cm,"
          f" 90% = {np.percentile(err, 90) * 100:.2f} cm")
    assert len(err) > 1000
    assert np.median(err) < 0.05


def test_lidar_points_fall_in_occupied_voxels(ds, synth_root: Path) -> None:
    frac, n = _occupied_fraction(ds, synth_root)
    print(f"\nLiDAR points in occupied voxels: {frac * 100:.2f}% of {n}")
    assert frac >= 0.99


@pytest.mark.slow
def test_full_resolution_world_is_consistent(tmp_path: Path) -> None:
    """The same checks on a 1600x900 world (the default resolution)."""
    from occdata.synth import SynthConfig, synthesize

    root = synthesize(SynthConfig(out=tmp_path / "full", scenes=1, samples=2, seed=5, progress=False))
    full = load_nuscenes(root, version="v1.0-mini")
    assert full.samples[0].cameras[0].width == 1600 and full.samples[0].cameras[0].height == 900
    err = _depth_errors(full, root)
    frac, _ = _occupied_fraction(full, root)
    print(f"\n1600x900: median depth error {np.median(err) * 100:.2f} cm over {len(err)} points; "
          f"occupied {frac * 100:.2f}%")
    assert np.median(err) < 0.05 and frac >= 0.99


def test_labels_format_and_content(ds, synth_root: Path) -> None:
    seen = np.zeros(18, bool)
    for sample in ds.samples:
        lab = _labels(synth_root, sample)
        assert set(lab) == {"semantics", "mask_lidar", "mask_camera"}
        for a in lab.values():
            assert a.shape == (200, 200, 16) and a.dtype == np.uint8
        assert set(np.unique(lab["mask_camera"])) <= {0, 1} and set(np.unique(lab["mask_lidar"])) <= {0, 1}
        seen[np.unique(lab["semantics"])] = True
        # Ground layer (z = 0 lies in voxel k = 2) is fully occupied; below it is free.
        assert (lab["semantics"][:, :, 2] != FREE_LABEL).all()
        assert (lab["semantics"][:, :, :2] == FREE_LABEL).all()
        assert 0.01 < lab["mask_camera"].mean() < 0.9
        # Nothing ever overlaps the ego car (x -1..4 m, y -1..1 m around the rear axle).
        assert (lab["semantics"][97:110, 97:102, 3:6] == FREE_LABEL).all()
    for c in (4, 11, 13, 15, 16, 7):  # car, driveable, sidewalk, manmade, vegetation, pedestrian
        assert seen[c], f"class {c} never labelled"


def test_mask_camera_keeps_the_surfaces_the_cameras_see(ds, synth_root: Path) -> None:
    """Independent check from the rendered depth maps: un-project every 4th pixel to key ego; the object
    voxels these surface points fall in are surfaces a camera sees, so mask_camera (Occ3D semantics,
    docs/visibility.md) must keep them. Free and ground voxels are camera-visible exactly where
    LiDAR-observed; the camera mask never leaves the LiDAR mask."""
    seen_visible = seen = 0
    for sample in ds.samples:
        lab = _labels(synth_root, sample)
        sem, cam_mask, lidar = lab["semantics"], lab["mask_camera"].astype(bool), lab["mask_lidar"].astype(bool)
        assert not (cam_mask & ~lidar).any()
        flat = (sem == FREE_LABEL) | np.isin(sem, GROUND_CLASSES)
        np.testing.assert_array_equal(cam_mask[flat], lidar[flat])
        hit = np.zeros(GRID.shape, bool)
        for i, cam in enumerate(sample.cameras):
            depth = _depth_of(synth_root, cam.token)[::4, ::4]
            v, u = np.nonzero(depth > 0)
            d = depth[v, u].astype(np.float64)
            rays = np.stack([u * 4.0, v * 4.0, np.ones(len(u))], 1) @ np.linalg.inv(cam.K).T
            p = transform_points(sample.T_keyego_from_cam(i), rays * d[:, None])
            idx = np.floor((p - np.asarray(GRID.lower)) / GRID.voxel_size).astype(int)
            ok = ((idx >= 0) & (idx < np.asarray(GRID.shape))).all(axis=1)
            hit[tuple(idx[ok].T)] = True
        objects = hit & ~flat
        seen += int(objects.sum())
        seen_visible += int((objects & cam_mask).sum())
    frac = seen_visible / seen
    print(f"\nobject voxels holding a rendered surface point: {frac * 100:.2f}% camera-visible (n={seen})")
    assert seen > 1000 and frac > 0.9



def _tables(root: Path) -> dict[str, list[dict]]:
    return {p.stem: json.loads(p.read_text()) for p in (root / "v1.0-mini").glob("*.json")}


def test_tables_complete_and_linked(synth_root: Path) -> None:
    t = _tables(synth_root)
    assert set(t) == {"attribute", "calibrated_sensor", "category", "ego_pose", "instance", "lidarseg", "log", "map",
                      "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility"}
    by = {name: {r["token"]: r for r in rows} for name, rows in t.items()}
    targets = {"first_sample_token": "sample", "last_sample_token": "sample",
               "first_annotation_token": "sample_annotation", "last_annotation_token": "sample_annotation"}
    for name, rows in t.items():
        for r in rows:
            if name != "visibility":
                assert len(r["token"]) == 32 and int(r["token"], 16) >= 0
            for key, val in r.items():
                if key.endswith("_token"):
                    target = targets.get(key, key[: -len("_token")])
                    assert val in by[target], f"{name}.{key} -> {val} unresolved"
                if key == "attribute_tokens":
                    assert all(a in by["attribute"] for a in val), f"{name}.{key} unresolved"
    assert [s["name"] for s in t["scene"]] == ["synth-0000", "synth-0001"]
    assert ["split=train" in s["description"] for s in t["scene"]] == [True, False]
    assert "split=val" in t["scene"][1]["description"]
    for m in t["map"]:
        assert (synth_root / m["filename"]).is_file() and all(lt in by["log"] for lt in m["log_tokens"])
    for scene in t["scene"]:
        chain = [scene["first_sample_token"]]
        while by["sample"][chain[-1]]["next"]:
            nxt = by["sample"][chain[-1]]["next"]
            assert by["sample"][nxt]["prev"] == chain[-1]
            chain.append(nxt)
        assert chain[-1] == scene["last_sample_token"] and len(chain) == scene["nbr_samples"] == 3
        ts = [by["sample"][s]["timestamp"] for s in chain]
        assert np.all(np.diff(ts) == 500_000)  # 2 Hz keyframes
    sd_per_sample: dict[str, dict[str, dict]] = {}
    for sd in t["sample_data"]:
        ch = by["sensor"][by["calibrated_sensor"][sd["calibrated_sensor_token"]]["sensor_token"]]["channel"]
        if sd["is_key_frame"]:  # LIDAR_TOP sweeps between keyframes: tests/test_sweeps_build.py
            sd_per_sample.setdefault(sd["sample_token"], {})[ch] = sd
        pose = by["ego_pose"][sd["ego_pose_token"]]
        assert pose["timestamp"] == sd["timestamp"] and pose["translation"][2] == 0.0
        assert (synth_root / sd["filename"]).is_file()
        if sd["prev"]:
            assert by["sample_data"][sd["prev"]]["next"] == sd["token"]
    assert len({sd["ego_pose_token"] for sd in t["sample_data"]}) == len(t["sample_data"]) == len(t["ego_pose"])
    for s_tok, chans in sd_per_sample.items():
        assert set(chans) == {*CAMERA_ORDER, "LIDAR_TOP"}
        t_lidar = chans["LIDAR_TOP"]["timestamp"]
        assert t_lidar == by["sample"][s_tok]["timestamp"]
        for ch in CAMERA_ORDER:
            dt = chans[ch]["timestamp"] - t_lidar
            assert -45_000 <= dt <= 0 and dt == CAMERA_TIME_OFFSETS_US[ch]
            assert chans[ch]["width"] == 400 and chans[ch]["height"] == 225


def test_rig_matches_real_nuscenes_calibration(real_nuscenes_root: Path) -> None:
    t = _tables(real_nuscenes_root)
    sensors = {r["token"]: r["channel"] for r in t["sensor"]}
    for cs in t["calibrated_sensor"]:
        ch = sensors[cs["sensor_token"]]
        rig = RIG[ch]
        assert np.allclose(rig.translation, cs["translation"]) and np.allclose(rig.rotation_wxyz, cs["rotation"])
        if cs["camera_intrinsic"]:
            K = np.array(cs["camera_intrinsic"])
            assert np.allclose(rig.intrinsic, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def test_reader_assigns_split_from_description(ds) -> None:
    assert [(s.name, s.split) for s in ds.scenes] == [("synth-0000", "train"), ("synth-0001", "val")]
    assert len(ds.samples) == 6


def test_ego_motion_is_realistic(ds) -> None:
    for scene in ds.scenes:
        samples = [s for s in ds.samples if s.scene_name == scene.name]
        xy = np.array([s.T_global_from_keyego[:2, 3] for s in samples])
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.5
        assert np.all((speed > 4.0) & (speed < 13.0)), speed
        for s in samples:
            # Each camera has its own ego pose: the car moved between camera triggers.
            poses = np.array([c.T_global_from_ego[:2, 3] for c in s.cameras])
            assert np.linalg.norm(poses[0] - s.T_global_from_keyego[:2, 3]) > 0.1


def test_images_show_classes(ds, synth_root: Path) -> None:
    """Images are real JPEGs with sky at the top and varied content."""
    cam = ds.samples[0].cameras[1]
    img = cv2.imread(str(cam.path))
    assert img.shape == (225, 400, 3)
    depth = _depth_of(synth_root, cam.token)
    sky = depth == 0
    assert sky[:20].mean() > 0.5 and not sky[-20:].any()
    assert img[sky].mean(axis=0)[0] > img[~sky].mean(axis=0)[0]  # sky is bluer (BGR) than the ground
    assert img.std() > 20
