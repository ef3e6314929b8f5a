"""The rig read from the tables, on the REAL Lyft Level 5 keyframes (7 cameras at 1920x1080, 3 LiDARs,
float timestamps, NaN sizes on LiDAR rows, `train_data/` layout): scan, build, and depth targets equal
to the official `lyft_dataset_sdk`'s `map_pointcloud_to_image` per camera and LiDAR (in the throwaway
devkit venv, OCCDATA_DEVKIT_PYTHON; scripts/devkit_env.sh installs the SDK there)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.nuscenes import load_nuscenes
from occdata.store.reader import open_store

LYFT_CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT",
                "CAM_FRONT_ZOOMED")
LYFT_LIDARS = ("LIDAR_TOP", "LIDAR_FRONT_LEFT", "LIDAR_FRONT_RIGHT")

# The SDK's projection of every LiDAR into every camera of every keyframe, as (u, v, depth) float64. The
# SDK keeps the points in float32 while it moves them through the global frame (~1.7 km from its origin
# here: float32 steps of 1.2e-4 m, up to ~0.1 px on CAM_FRONT_ZOOMED's 3962 px focal length at 3 m), so
# with argv[5] == "float64" its point loader hands it float64 points; its chain and margins are unchanged.
SDK_PROJECT = r'''
import sys
import numpy as np
from lyft_dataset_sdk.lyftdataset import LyftDataset
from lyft_dataset_sdk.utils import data_classes
if sys.argv[5] == "float64":
    load = data_classes.LidarPointCloud.from_file.__func__
    def from_file_float64(cls, path):
        pc = load(cls, path)
        pc.points = pc.points.astype(np.float64)
        return pc
    data_classes.LidarPointCloud.from_file = classmethod(from_file_float64)
lyft = LyftDataset(data_path=sys.argv[1], json_path=sys.argv[1] + "/train_data", verbose=False)
cams, lidars = sys.argv[3].split(","), sys.argv[4].split(",")
out = {}
for s in lyft.sample:
    for cam in cams:
        for lidar in lidars:
            pts, depth, _ = lyft.explorer.map_pointcloud_to_image(s["data"][lidar], s["data"][cam])
            out[f"{s['token']}/{cam}/{lidar}"] = np.stack([pts[0], pts[1], depth], axis=1)
np.savez(sys.argv[2], **out)
'''


@pytest.fixture(scope="module")
def lyft_store(real_lyft_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lyft") / "lyft.zarr"
    res = CliRunner().invoke(main, ["build", "--root", str(real_lyft_root), "--out", str(out), "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "rig: 7 cameras" in res.output and "3 LiDARs (LIDAR_TOP reference" in res.output
    return out


def test_the_rig_comes_from_the_tables(real_lyft_root: Path) -> None:
    ds = load_nuscenes(real_lyft_root, sweeps=True, check_files=True)
    assert ds.version == "train_data" and len(ds.samples) == 16
    assert ds.rig.cameras == LYFT_CAMERAS and ds.rig.lidars == LYFT_LIDARS and ds.rig.left_out == ()
    s = ds.samples[0]
    assert [c.channel for c in s.cameras] == list(LYFT_CAMERAS)
    assert [r.channel for r in s.lidars] == list(LYFT_LIDARS)
    assert {(c.width, c.height) for c in s.cameras} == {(1920, 1080)}
    # 1557858039302414.8 in sample.json: rounded to the nearest microsecond
    assert s.timestamp == 1557858039302415
    # every sample_data row is a keyframe: no sweeps in between, and the history is the earlier keyframes
    assert all(not x.sweeps and all(not w for w in x.extra_sweeps) for x in ds.samples)
    hist = ds.lidar_histories(2, 2)
    assert [r.channel for r in hist] == [c for c in LYFT_LIDARS for _ in range(2)]
    assert [r.token for r in hist[:2]] == [ds.samples[1].lidar.token, ds.samples[0].lidar.token]


def test_scan_prints_the_rig_and_names_what_it_leaves_out(real_lyft_root: Path) -> None:
    res = CliRunner().invoke(main, ["scan", "--root", str(real_lyft_root)])
    assert res.exit_code == 0, res.output
    assert "rig: 7 cameras (CAM_FRONT_LEFT, " in res.output and "CAM_FRONT_ZOOMED), 3 LiDARs" in res.output
    res = CliRunner().invoke(main, ["scan", "--root", str(real_lyft_root), "--cameras", "CAM_BACK,CAM_FRONT",
                                    "--lidars", "LIDAR_FRONT_LEFT,LIDAR_TOP", "--json"])
    summary = json.loads(res.output)
    assert summary["rig"] == {"cameras": ["CAM_BACK", "CAM_FRONT"], "lidars": ["LIDAR_TOP", "LIDAR_FRONT_LEFT"],
                              "reference_lidar": "LIDAR_TOP"}
    assert summary["left_out"] == [
        "CAM_BACK_LEFT, CAM_BACK_RIGHT, CAM_FRONT_LEFT, CAM_FRONT_RIGHT, CAM_FRONT_ZOOMED (camera: not in --cameras)",
        "LIDAR_FRONT_RIGHT (lidar: not in --lidars)"]
    res = CliRunner().invoke(main, ["scan", "--root", str(real_lyft_root), "--cameras", "CAM_FRONT,CAM_SIDE"])
    assert res.exit_code != 0
    assert "--cameras: CAM_SIDE is not a camera with keyframe rows in the tables" in res.output


def test_the_store_holds_all_seven_cameras_and_its_rig(lyft_store: Path) -> None:
    reader = open_store(lyft_store)
    assert reader.n_cams == 7 and reader.attrs["camera_order"] == list(LYFT_CAMERAS)
    assert reader.attrs["rig"] == {"cameras": list(LYFT_CAMERAS), "lidars": list(LYFT_LIDARS),
                                   "reference_lidar": "LIDAR_TOP"}
    assert reader.group["images/offsets"].shape == (16, 7, 2)
    assert len(reader.jpeg_bytes(0)) == 7
    assert reader.attrs["depth"]["source"] == "keyframe LIDAR_TOP + LIDAR_FRONT_LEFT + LIDAR_FRONT_RIGHT"
    res = CliRunner().invoke(main, ["verify", "--store", str(lyft_store), "--no-progress"])
    assert res.exit_code == 0, res.output


@pytest.mark.skipif(not os.environ.get("OCCDATA_DEVKIT_PYTHON"),
                    reason="set OCCDATA_DEVKIT_PYTHON to the devkit venv's python (scripts/devkit_env.sh)")
def test_depth_targets_equal_the_lyft_sdk_projection_of_every_lidar(
    real_lyft_root: Path, lyft_store: Path, tmp_path: Path
) -> None:
    """Per camera, the stored (u, v, depth) rows are the SDK's points of LIDAR_TOP, then LIDAR_FRONT_LEFT,
    then LIDAR_FRONT_RIGHT, in file order. The SDK keeps 1 < u < W - 1 and 1 < v < H - 1 and depth > 0;
    we keep 0 <= u < W, 0 <= v < H: compared on the SDK's window."""
    sdk_file = tmp_path / "sdk.npz"
    res = subprocess.run([os.environ["OCCDATA_DEVKIT_PYTHON"], "-c", SDK_PROJECT, str(real_lyft_root), str(sdk_file),
                          ",".join(LYFT_CAMERAS), ",".join(LYFT_LIDARS), "float64"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    reader = open_store(lyft_store)
    per_camera: dict[str, list[int]] = {c: [0, 0] for c in LYFT_CAMERAS}
    with np.load(sdk_file, allow_pickle=False) as sdk:
        for i in range(reader.n_samples):
            token = reader.token(i)
            for c, (cam, ours) in enumerate(zip(LYFT_CAMERAS, reader.depth_points(i), strict=True)):
                W, H = reader.group["cam/image_size"][i, c]
                truth = np.concatenate([sdk[f"{token}/{cam}/{lidar}"] for lidar in LYFT_LIDARS])
                keep = (ours[:, 0] > 1) & (ours[:, 0] < W - 1) & (ours[:, 1] > 1) & (ours[:, 1] < H - 1)
                assert keep.sum() == len(truth), (token, cam)
                # float32 storage of u, v < 1920: steps of 1.2e-4 px
                np.testing.assert_allclose(ours[keep], truth, atol=1e-3, rtol=0)
                per_camera[cam][0] += len(truth)
                per_camera[cam][1] += int((~keep).sum())
    assert all(n > 0 for n, _ in per_camera.values()), per_camera


@pytest.mark.slow
def test_real_lyft_labels_train_export_predict_and_view(real_lyft_root: Path, tmp_path: Path) -> None:
    """The whole chain on the real Lyft keyframes: labels by carving (no boxes), a store with them, nano for
    an epoch, ONNX export with the 7-camera rig baked in, predictions, and the viewer's offline page."""
    from cli.fastocc_cli import main as fastocc_main

    def ok(group, args: list[str]) -> str:  # noqa: ANN001 - a click group
        res = CliRunner().invoke(group, args)
        assert res.exit_code == 0, (args[0], res.output)
        return res.output

    gts, store, run = tmp_path / "gts", tmp_path / "lyft.zarr", tmp_path / "run"
    assert "moving objects by free-space carving" in ok(main, ["labels", "--root", str(real_lyft_root), "--out",
                                                               str(gts), "--no-progress"])
    ok(main, ["build", "--root", str(real_lyft_root), "--gts", str(gts), "--out", str(store), "--no-progress"])
    assert open_store(store).group["labels/present"][:].all()
    conf = tmp_path / "nano.toml"
    conf.write_text('preset = "nano"\ninput_hw = [128, 352]\nepochs = 1\nbatch_size = 2\nworkers = 0\nval_every = 0\n')
    ok(fastocc_main, ["train", "--store", str(store), "--config", str(conf), "--out", str(run), "--no-progress"])
    out = ok(fastocc_main, ["export", "--checkpoint", str(run / "last.pt"), "--rig", str(store),
                            "--out", str(tmp_path / "lyft.onnx")])
    assert "PASS" in out
    meta = json.loads((tmp_path / "lyft.json").read_text())
    assert meta["camera_order"] == list(LYFT_CAMERAS) and meta["inputs"]["images"]["shape"][1] == 7
    from fastocc.deploy import Predictor

    reader = open_store(store)
    assert Predictor(tmp_path / "lyft.onnx")(reader.images(3)).shape == (200, 200, 16)  # 7 raw 1920x1080 images
    ok(fastocc_main, ["predict", "--checkpoint", str(run / "last.pt"), "--store", str(store), "--split",
                      "train", "--out", str(tmp_path / "pred"), "--no-progress"])
    assert len(list((tmp_path / "pred").glob("*/*/labels.npz"))) == 16
    ok(main, ["view", "--store", str(store), "--pred", str(tmp_path / "pred"), "--export", str(tmp_path / "v.html")])
    assert (tmp_path / "v.html").stat().st_size > 1_000_000
