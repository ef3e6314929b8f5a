"""`occdata synth --rig lyft|truckscenes`: the trees carry each dataset's rig, rates, layout, file formats
and table quirks; scan and build read them (every camera, every LiDAR); and the official devkits --
lyft_dataset_sdk and truckscenes-devkit, in the throwaway devkit venv (OCCDATA_DEVKIT_PYTHON) -- load
them and are the truth for points in the ego frame, LiDAR-to-image projection (our stored depth
targets) and boxes (our reader's `boxes_for_lidar`)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.geometry import transform_points
from occdata.nuscenes import boxes_for_lidar, load_annotations, load_lidar_points, load_nuscenes
from occdata.nuscenes.pointfiles import read_pcd
from occdata.store.reader import open_store

LYFT_CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT",
                "CAM_FRONT_ZOOMED")  # the reader's order: nuScenes' six in model order, then by name
LYFT_LIDARS = ("LIDAR_TOP", "LIDAR_FRONT_LEFT", "LIDAR_FRONT_RIGHT")
TRUCK_CAMERAS = ("CAMERA_LEFT_BACK", "CAMERA_LEFT_FRONT", "CAMERA_RIGHT_BACK", "CAMERA_RIGHT_FRONT")
TRUCK_LIDARS = ("LIDAR_LEFT", "LIDAR_REAR", "LIDAR_RIGHT", "LIDAR_TOP_FRONT", "LIDAR_TOP_LEFT", "LIDAR_TOP_RIGHT")
SIZE = (96, 54)

needs_devkit = pytest.mark.skipif(
    not os.environ.get("OCCDATA_DEVKIT_PYTHON"),
    reason="set OCCDATA_DEVKIT_PYTHON to the devkit venv's python (scripts/devkit_env.sh)")


def _synth(tmp_path_factory: pytest.TempPathFactory, rig: str, samples: int) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp(rig)
    res = CliRunner().invoke(main, ["synth", "--rig", rig, "--out", str(base / "tree"), "--scenes", "1", "--samples",
                                    str(samples), "--width", str(SIZE[0]), "--height", str(SIZE[1]), "--no-progress"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["build", "--root", str(base / "tree"), "--out", str(base / "s.zarr"),
                                    "--no-progress"])
    assert res.exit_code == 0, res.output
    return base / "tree", base / "s.zarr"


@pytest.fixture(scope="module")
def lyft(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return _synth(tmp_path_factory, "lyft", 3)


@pytest.fixture(scope="module")
def truck(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return _synth(tmp_path_factory, "truckscenes", 2)


def _rows(root: Path, version: str, table: str) -> list[dict]:
    return json.loads((root / version / f"{table}.json").read_text())


# --- the trees ---------------------------------------------------------------------------------------
def test_the_lyft_tree_has_lyfts_layout_rates_and_quirks(lyft: tuple[Path, Path]) -> None:
    root, _ = lyft
    assert sorted(p.name for p in root.iterdir()) == ["depth", "gts", "maps", "train_data", "train_images",
                                                       "train_lidar"]
    sd = _rows(root, "train_data", "sample_data")
    cams = [r for r in sd if r["fileformat"] == "jpeg"]
    lidars = [r for r in sd if r["fileformat"] == "bin"]
    assert len(cams) == 7 * 3 and len(lidars) == 3 * 3 and len(sd) == 30 and all(r["is_key_frame"] for r in sd)
    assert all(r["filename"].startswith("train_images/") and r["filename"].endswith(".jpeg") for r in cams)
    assert all(r["filename"].startswith("train_lidar/") and r["filename"].endswith(".bin") for r in lidars)
    assert all(np.isnan(r["width"]) and np.isnan(r["height"]) for r in lidars)
    assert {(r["width"], r["height"]) for r in cams} == {SIZE}
    for table in ("sample", "sample_data", "ego_pose"):  # microseconds as floats, 0.25 us off the integer
        assert all(isinstance(r["timestamp"], float) and r["timestamp"] % 1 == 0.25
                   for r in _rows(root, "train_data", table))
    times = [r["timestamp"] for r in _rows(root, "train_data", "sample")]
    assert np.diff(times).tolist() == [200_000.0, 200_000.0]  # 5 Hz keyframes
    assert not (root / "train_data" / "lidarseg.json").exists()
    points = np.fromfile(root / lidars[0]["filename"], dtype=np.float32)
    assert points.size > 0 and points.size % 5 == 0


def test_the_truckscenes_tree_has_truckscenes_layout_rates_and_quirks(truck: tuple[Path, Path]) -> None:
    root, _ = truck
    sd = _rows(root, "v1.0-mini", "sample_data")
    sensors = {r["token"]: r for r in _rows(root, "v1.0-mini", "sensor")}
    assert sorted(r["channel"] for r in sensors.values()) == sorted(TRUCK_CAMERAS + TRUCK_LIDARS)
    cs = {r["token"]: sensors[r["sensor_token"]]["channel"] for r in _rows(root, "v1.0-mini", "calibrated_sensor")}
    for lidar in TRUCK_LIDARS:
        rows = sorted((r for r in sd if cs[r["calibrated_sensor_token"]] == lidar), key=lambda r: r["timestamp"])
        # 10 Hz: 2 keyframes and the 4 sweeps between them, every 100 ms
        assert [r["is_key_frame"] for r in rows] == [True, False, False, False, False, True]
        assert set(np.diff([r["timestamp"] for r in rows]).tolist()) == {100_000}
        assert all(r["fileformat"] == "pcd" and r["filename"].endswith(".pcd") for r in rows)
        assert rows[1]["filename"].startswith(f"sweeps/{lidar}/") and rows[0]["filename"].startswith("samples/")
        pcd = read_pcd(root / rows[2]["filename"])  # per-point timestamps: the sweep's (one-instant spin)
        assert pcd.timestamps is not None and set(pcd.timestamps.tolist()) == {rows[2]["timestamp"]}
    poses = _rows(root, "v1.0-mini", "ego_pose")
    assert all(r["translation"][2] == 0.0 and r["translation"][0] > 690_000 and r["translation"][1] > 5_335_000
               for r in poses)  # UTM-like, z = 0
    for table in ("ego_motion_cabin", "ego_motion_chassis"):
        motion = _rows(root, "v1.0-mini", table)
        assert [(r["token"], r["timestamp"]) for r in motion] == [(r["token"], r["timestamp"]) for r in poses]
        assert all(0 < r["vx"] < 30 and abs(r["vy"]) < 0.5 for r in motion)  # driving forwards
    names = sorted(p.stem for p in (root / "v1.0-mini").iterdir())
    assert "ego_motion_cabin" in names and "lidarseg" not in names and "map" not in names


@pytest.mark.parametrize("rig", ["lyft", "truckscenes"])
def test_scan_and_the_store_hold_the_whole_rig(rig: str, lyft: tuple[Path, Path], truck: tuple[Path, Path]) -> None:
    (root, store), cams, lidars, n = {"lyft": (lyft, LYFT_CAMERAS, LYFT_LIDARS, 3),
                                      "truckscenes": (truck, TRUCK_CAMERAS, TRUCK_LIDARS, 2)}[rig]
    ds = load_nuscenes(root, sweeps=True, check_files=True)
    assert ds.rig.cameras == cams and ds.rig.lidars == lidars and ds.rig.left_out == ()
    assert len(ds.samples) == n and all(len(s.sweeps) == (0 if rig == "lyft" else 4 * (k > 0))
                                        for k, s in enumerate(ds.samples))
    res = CliRunner().invoke(main, ["scan", "--root", str(root)])
    assert res.exit_code == 0 and f"rig: {len(cams)} cameras" in res.output, res.output
    reader = open_store(store)
    assert reader.n_cams == len(cams) and reader.attrs["camera_order"] == list(cams)
    assert reader.attrs["rig"] == {"cameras": list(cams), "lidars": list(lidars), "reference_lidar": lidars[0]}
    assert reader.attrs["depth"]["source"] == "keyframe " + " + ".join(lidars)
    assert (reader.group["cam/image_size"][:] == SIZE).all()
    assert reader.n_samples == n and all(len(reader.depth_points(i)) == len(cams) for i in range(n))


# --- the devkits -------------------------------------------------------------------------------------
# lyft_dataset_sdk keeps points in float32 through the global frame; as tests/test_rig_lyft.py, its
# point loader is given float64 points (argv[3] == "float64"), its chain unchanged.
LYFT_SDK = r'''
import json, sys
import numpy as np
from lyft_dataset_sdk.lyftdataset import LyftDataset
from lyft_dataset_sdk.utils import data_classes
from pyquaternion import Quaternion
load = data_classes.LidarPointCloud.from_file.__func__
def from_file_float64(cls, path):
    pc = load(cls, path)
    pc.points = pc.points.astype(np.float64)
    return pc
data_classes.LidarPointCloud.from_file = classmethod(from_file_float64)
lyft = LyftDataset(data_path=sys.argv[1], json_path=sys.argv[1] + "/train_data", verbose=False)
out, boxes = {}, {}
for s in lyft.sample:
    for ch, sd_tok in s["data"].items():
        sd = lyft.get("sample_data", sd_tok)
        if sd["fileformat"] != "bin":
            continue
        pc = data_classes.LidarPointCloud.from_file(lyft.get_sample_data_path(sd_tok))
        cs = lyft.get("calibrated_sensor", sd["calibrated_sensor_token"])
        pc.rotate(Quaternion(cs["rotation"]).rotation_matrix)
        pc.translate(np.array(cs["translation"]))
        out[f"ego/{sd_tok}"] = pc.points[:3].T
        boxes[sd_tok] = [[b.token, *map(float, b.center), *map(float, b.wlh), *map(float, b.orientation.elements)]
                         for b in lyft.get_boxes(sd_tok)]
        for cam in [c for c in s["data"] if c.startswith("CAM")]:
            pts, depth, _ = lyft.explorer.map_pointcloud_to_image(sd_tok, s["data"][cam])
            out[f"{s['token']}/{cam}/{ch}"] = np.stack([pts[0], pts[1], depth], axis=1)
np.savez(sys.argv[2], **out)
json.dump(boxes, open(sys.argv[2] + ".boxes.json", "w"))
'''

# truckscenes-devkit's explorer imports open3d (for its 3D viewer only): a stub module stands in, and
# map_pointcloud_to_image is given a Colormap object and no normalisation (both only colour the points).
TRUCK_DEVKIT = r'''
import json, sys, types
sys.modules["open3d"] = types.ModuleType("open3d")
import numpy as np
from matplotlib import colormaps
from pyquaternion import Quaternion
from truckscenes import TruckScenes
from truckscenes.utils.data_classes import LidarPointCloud
ts = TruckScenes(version="v1.0-mini", dataroot=sys.argv[1], verbose=False)
out, boxes = {}, {}
for sd in ts.sample_data:
    if sd["sensor_modality"] != "lidar":
        continue
    boxes[sd["token"]] = [[b.token, *map(float, b.center), *map(float, b.wlh), *map(float, b.orientation.elements)]
                          for b in ts.get_boxes(sd["token"])]
for s in ts.sample:
    for ch, sd_tok in s["data"].items():
        sd = ts.get("sample_data", sd_tok)
        if sd["sensor_modality"] != "lidar":
            continue
        pc = LidarPointCloud.from_file(ts.get_sample_data_path(sd_tok))
        out[f"times/{sd_tok}"] = pc.timestamps[0]
        cs = ts.get("calibrated_sensor", sd["calibrated_sensor_token"])
        pc.rotate(Quaternion(cs["rotation"]).rotation_matrix)
        pc.translate(np.array(cs["translation"]))
        out[f"ego/{sd_tok}"] = pc.points[:3].T
        for cam in [c for c in s["data"] if c.startswith("CAMERA")]:
            pts, _, _ = ts.explorer.map_pointcloud_to_image(sd_tok, s["data"][cam], cmap=colormaps["viridis"],
                                                             cnorm=False)
            out[f"{s['token']}/{cam}/{ch}"] = pts.T
np.savez(sys.argv[2], **out)
json.dump(boxes, open(sys.argv[2] + ".boxes.json", "w"))
'''


def _devkit(script: str, root: Path, out: Path) -> tuple[dict[str, np.ndarray], dict[str, list]]:
    res = subprocess.run([os.environ["OCCDATA_DEVKIT_PYTHON"], "-c", script, str(root), str(out)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    with np.load(out, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    return arrays, json.loads(Path(str(out) + ".boxes.json").read_text())


def _compare(root: Path, store: Path, devkit: dict[str, np.ndarray], boxes: dict[str, list], cams: tuple[str, ...],
             lidars: tuple[str, ...], truck: bool) -> dict[str, int]:
    ds = load_nuscenes(root, sweeps=True, check_files=True)
    ann = load_annotations(root, ds.version)
    reader = open_store(store)
    per_camera = dict.fromkeys(cams, 0)
    n_boxes = 0
    for i, s in enumerate(ds.samples):
        # points in the ego frame
        for rec in s.lidars:
            ours = transform_points(rec.T_ego_from_lidar, load_lidar_points(rec.path)[:, :3].astype(np.float64))
            np.testing.assert_allclose(ours, devkit[f"ego/{rec.token}"], atol=1e-5, rtol=0)
        # projection: the stored (u, v, depth) rows per camera are every LiDAR's points in rig order; the
        # devkits keep 1 < u < W - 1, 1 < v < H - 1, depth > 1 m: compared on that window
        assert reader.token(i) == s.token
        for c, (cam, ours) in enumerate(zip(cams, reader.depth_points(i), strict=True)):
            W, H = reader.group["cam/image_size"][i, c]
            truth = np.concatenate([devkit[f"{s.token}/{cam}/{lidar}"] for lidar in lidars])
            keep = (ours[:, 0] > 1) & (ours[:, 0] < W - 1) & (ours[:, 1] > 1) & (ours[:, 1] < H - 1) & (ours[:, 2] > 1)
            assert keep.sum() == len(truth), (s.token, cam)
            cols = 2 if truck else 3  # truckscenes-devkit returns the depth only as colour: u, v compared
            np.testing.assert_allclose(ours[keep][:, :cols], truth[:, :cols], atol=1e-3, rtol=0)
            per_camera[cam] += len(truth)
        # boxes at the reference LiDAR's keyframe and sweeps (TruckScenes': interpolated); the other LiDARs'
        # keyframes get the sample's boxes as stored (`boxes_for_lidar` takes the reference LiDAR's rows only)
        for rec, ref in [(r, boxes[r.token]) for r in (s.lidar, *s.sweeps)] + [(s.lidar, boxes[r.token])
                                                                              for r in s.extra_lidars]:
            ours_b = boxes_for_lidar(ann, ds, i, rec)
            assert [b.token for b in ours_b] == [r[0] for r in ref], rec.token
            for b, r in zip(ours_b, ref, strict=True):
                np.testing.assert_allclose(b.center_global, r[1:4], atol=1e-6, rtol=0)
                np.testing.assert_allclose(b.size_wlh, r[4:7], atol=0, rtol=0)
                q, rq = np.asarray(b.rotation_wxyz), np.asarray(r[7:11])
                assert min(np.abs(q - rq).max(), np.abs(q + rq).max()) < 1e-9
            n_boxes += len(ref)
    assert n_boxes > 0 and all(n > 0 for n in per_camera.values()), (n_boxes, per_camera)
    return per_camera


@needs_devkit
def test_lyft_sdk_loads_the_tree_and_agrees(lyft: tuple[Path, Path], tmp_path: Path) -> None:
    root, store = lyft
    devkit, boxes = _devkit(LYFT_SDK, root, tmp_path / "lyft.npz")
    _compare(root, store, devkit, boxes, LYFT_CAMERAS, LYFT_LIDARS, truck=False)


@needs_devkit
def test_truckscenes_devkit_loads_the_tree_and_agrees(truck: tuple[Path, Path], tmp_path: Path) -> None:
    root, store = truck
    devkit, boxes = _devkit(TRUCK_DEVKIT, root, tmp_path / "truck.npz")
    ds = load_nuscenes(root, sweeps=True)
    for s in ds.samples:  # the per-point timestamps the devkit reads are ours
        for rec in s.lidars:
            times = read_pcd(rec.path).timestamps
            assert times is not None
            np.testing.assert_array_equal(times, devkit[f"times/{rec.token}"])
    _compare(root, store, devkit, boxes, TRUCK_CAMERAS, TRUCK_LIDARS, truck=True)
