"""`occdata synth` writes 20 Hz LIDAR_TOP sweeps; `occdata build --lidar-sweeps N` aggregates them
into the depth targets (checked against the synthetic world's rendered depth, the independent truth)."""

from __future__ import annotations

import json
import os
import subprocess
import textwrap
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.constants import CAMERA_ORDER
from occdata.nuscenes import load_nuscenes
from occdata.store.layout import token_str
from occdata.store.reader import open_store

N_SWEEPS = 9


def _build(root: Path, out: Path, *extra: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["build", "--root", str(root), "--out", str(out), "--no-progress", *extra])
    return res.exit_code, res.output


@pytest.fixture(scope="module")
def sweep_store(synth_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sweeps") / "data.zarr"
    code, output = _build(synth_root, out, "--lidar-sweeps", str(N_SWEEPS))
    assert code == 0, output
    return out


def test_synth_writes_20hz_sweeps_with_chains_and_poses(synth_root: Path) -> None:
    t = {n: json.loads((synth_root / "v1.0-mini" / f"{n}.json").read_text())
         for n in ("sample_data", "ego_pose", "sample", "calibrated_sensor", "sensor")}
    by_tok = {sd["token"]: sd for sd in t["sample_data"]}
    pose = {p["token"]: p for p in t["ego_pose"]}
    sweeps = [sd for sd in t["sample_data"] if not sd["is_key_frame"]]
    assert len(sweeps) == 2 * 2 * 9  # 2 scenes x 2 keyframe intervals x 9
    for sd in sweeps:
        assert sd["filename"].startswith("sweeps/LIDAR_TOP/") and sd["fileformat"] == "pcd"
        pts = np.fromfile(synth_root / sd["filename"], dtype=np.float32).reshape(-1, 5)
        assert len(pts) > 10_000 and np.isfinite(pts).all()
        assert pose[sd["ego_pose_token"]]["timestamp"] == sd["timestamp"]
        assert by_tok[sd["prev"]]["next"] == sd["token"] and by_tok[sd["next"]]["prev"] == sd["token"]
        assert by_tok[sd["next"]]["timestamp"] - sd["timestamp"] == 50_000  # 20 Hz
    # The car moves between sweeps: every sweep has its own ego pose.
    assert len({tuple(pose[sd["ego_pose_token"]]["translation"]) for sd in sweeps}) == len(sweeps)
    ds = load_nuscenes(synth_root, sweeps=True)
    assert [len(s.sweeps) for s in ds.samples] == [0, 9, 9, 0, 9, 9]


def test_build_aggregates_sweeps_keyframe_points_first(sweep_store: Path, synth_store: Path) -> None:
    many, one = open_store(sweep_store), open_store(synth_store)
    assert zarr.open_group(sweep_store, mode="r").attrs["depth"]["lidar_sweeps"] == N_SWEEPS
    assert zarr.open_group(sweep_store, mode="r").attrs["build_identity"]["options"]["lidar_sweeps"] == N_SWEEPS
    for i in range(one.n_samples):
        for a, b in zip(many.depth_points(i), one.depth_points(i), strict=True):
            np.testing.assert_array_equal(a[: len(b)], b)  # the keyframe sweep's points come first, unchanged
            if i % 3:  # keyframes after the first of their scene have 9 previous sweeps
                assert len(a) > 5 * len(b)
            else:
                assert len(a) == len(b)


def _signed_depth_errors(store_path: Path, synth_root: Path) -> np.ndarray:
    """Stored depth minus the rendered depth at the nearest pixel, every point of every camera."""
    store = open_store(store_path)
    cam_tokens = zarr.open_group(store_path, mode="r")["cam/token"][:]
    errs = []
    for i in range(store.n_samples):
        for c, uvd in enumerate(store.depth_points(i)):
            dmap = np.load(synth_root / "depth" / f"{token_str(cam_tokens[i, c])}.npy")
            u = np.clip(np.floor(uvd[:, 0] + 0.5).astype(int), 0, dmap.shape[1] - 1)
            v = np.clip(np.floor(uvd[:, 1] + 0.5).astype(int), 0, dmap.shape[0] - 1)
            errs.append(uvd[:, 2] - dmap[v, u])
    return np.concatenate(errs)


def test_aggregated_targets_match_the_rendered_depth(sweep_store: Path, synth_store: Path, synth_root: Path) -> None:
    """Motion compensation through global to each camera's own timestamp puts the static world's sweep
    points on the rendered surfaces. Points well IN FRONT of the rendered surface (in free space) come
    only from moving actors and depth edges: 1.4% for the keyframe, ~4% aggregated over 9 sweeps,
    while the keyframe's ego pose used for every sweep (no motion compensation) gives ~20%. Points
    BEHIND the surface are also occluded points seen from the older LiDAR positions."""
    key, many = _signed_depth_errors(synth_store, synth_root), _signed_depth_errors(sweep_store, synth_root)
    print(f"\nin front by > 0.5 m: keyframe {(key < -0.5).mean():.4f}, {N_SWEEPS} sweeps {(many < -0.5).mean():.4f}")
    assert len(many) > 5 * len(key) > 100_000
    assert (key < -0.5).mean() < 0.03 and (many < -0.5).mean() < 0.08, ((key < -0.5).mean(), (many < -0.5).mean())
    assert np.median(np.abs(many)) < 0.05


def test_resume_with_another_sweep_count_is_refused(sweep_store: Path, synth_root: Path, tmp_path: Path) -> None:
    code, output = _build(synth_root, sweep_store, "--resume")
    assert code == 1 and "--lidar-sweeps: store 9, now 0" in output, output
    assert len(output.strip().splitlines()) == 2  # the labels line, then one error line


def test_store_from_before_sweeps_resumes_as_zero_sweeps(synth_store: Path, synth_root: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "old.zarr"
    shutil.copytree(synth_store, copy)
    g = zarr.open_group(copy, mode="r+")
    ident = dict(g.attrs["build_identity"])
    ident["options"] = {k: v for k, v in ident["options"].items() if k != "lidar_sweeps"}
    g.attrs["build_identity"] = ident
    code, output = _build(synth_root, copy, "--resume")
    assert code == 0, output
    code, output = _build(synth_root, copy, "--resume", "--lidar-sweeps", "1")
    assert code == 1 and "--lidar-sweeps: store 0, now 1" in output, output


def _tree_without(synth_root: Path, tmp_path: Path, drop_sweeps: bool) -> Path:
    root = tmp_path / "tree"
    root.mkdir()
    for name in ("v1.0-mini", "samples", "gts", "maps", "depth", *(() if drop_sweeps else ("sweeps",))):
        os.symlink(synth_root / name, root / name)
    return root


def test_missing_sweep_files_give_one_line_and_no_store(synth_root: Path, tmp_path: Path) -> None:
    root = _tree_without(synth_root, tmp_path, drop_sweeps=True)
    out = tmp_path / "s.zarr"
    code, output = _build(root, out, "--lidar-sweeps", "4")
    line = output.strip().splitlines()[-1]
    assert code == 1 and line.startswith("Error: --lidar-sweeps 4: missing sweep file "), output
    assert "/sweeps/LIDAR_TOP/synth-0000__LIDAR_TOP__" in line and "0 of the 16 sweep files needed were found" in line
    assert not out.exists() and not list(tmp_path.glob("s.zarr*"))  # nothing half-written
    code, output = _build(root, out)  # the keyframes alone build as before
    assert code == 0, output


def test_one_missing_sweep_is_named(synth_root: Path, tmp_path: Path) -> None:
    root = tmp_path / "tree"
    root.mkdir()
    for name in ("v1.0-mini", "samples", "gts", "maps", "depth"):
        os.symlink(synth_root / name, root / name)
    (root / "sweeps" / "LIDAR_TOP").mkdir(parents=True)
    files = sorted((synth_root / "sweeps" / "LIDAR_TOP").iterdir())
    for f in files:
        os.symlink(f, root / "sweeps" / "LIDAR_TOP" / f.name)
    victim = root / "sweeps" / "LIDAR_TOP" / files[20].name
    victim.unlink()
    code, output = _build(root, tmp_path / "s.zarr", "--lidar-sweeps", str(N_SWEEPS))
    assert code == 1 and f"missing sweep file {victim} " in output, output
    assert f"{len(files) - 1} of the {len(files)} sweep files needed were found" in output


# The official devkit aggregates the sweeps into the keyframe's LiDAR frame (from_file_multisweep),
# then its own map_pointcloud_to_image chain projects the aggregate: its LidarPointCloud.from_file
# is pointed at the aggregate for that call, so every transform and mask is the devkit's code.
DEVKIT_MULTISWEEP = textwrap.dedent("""
    import sys
    import numpy as np
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.data_classes import LidarPointCloud
    root, nsweeps, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    nusc = NuScenes(version="v1.0-mini", dataroot=root, verbose=False)
    original = LidarPointCloud.__dict__["from_file"]
    res = {}
    for sample in nusc.sample:
        agg, _ = LidarPointCloud.from_file_multisweep(nusc, sample, "LIDAR_TOP", "LIDAR_TOP", nsweeps=nsweeps)
        LidarPointCloud.from_file = classmethod(lambda cls, path: cls(agg.points.copy()))
        try:
            for ch in ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"):
                pts, depth, im = nusc.explorer.map_pointcloud_to_image(sample["data"]["LIDAR_TOP"],
                                                                       sample["data"][ch], min_dist=1.0)
                res[sample["token"] + "/" + ch] = np.vstack([pts[:2], depth[None]]).T
                res[sample["token"] + "/" + ch + "/size"] = np.array(im.size)
        finally:
            LidarPointCloud.from_file = original
    np.savez(out, **res)
""")


def _devkit_rule(uvd: np.ndarray, width: int, height: int) -> np.ndarray:
    u, v, d = uvd[:, 0], uvd[:, 1], uvd[:, 2]
    return (d > 1.0) & (u > 1) & (u < width - 1) & (v > 1) & (v < height - 1)


def _at_border(uvd: np.ndarray, width: int, height: int, px: float = 0.03) -> np.ndarray:
    """Points whose keep/drop decision float32 rounding can flip: within `px` of a border line, or
    depth within 1e-4 m of the 1 m limit."""
    u, v, d = uvd[:, 0].astype(np.float64), uvd[:, 1].astype(np.float64), uvd[:, 2].astype(np.float64)
    dist = np.min(np.abs(np.stack([u - 1, u - (width - 1), v - 1, v - (height - 1)])), axis=0)
    return (dist < px) | (np.abs(d - 1.0) < 1e-4)


def _match_in_order(ours: np.ndarray, theirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Both lists follow the aggregate's point order (keyframe, then sweeps nearest first), and differ
    only by points that one side kept at a border: walk them together. Returns matched index pairs
    and the unmatched indices of each side."""
    i = j = 0
    mi, mj, oi, oj = [], [], [], []
    while i < len(ours) and j < len(theirs):
        if np.abs(ours[i, :2] - theirs[j, :2]).max() < 0.5:
            mi.append(i)
            mj.append(j)
            i, j = i + 1, j + 1
        elif j + 1 < len(theirs) and np.abs(ours[i, :2] - theirs[j + 1, :2]).max() < 0.5:
            oj.append(j)
            j += 1
        else:
            oi.append(i)
            i += 1
    oi += range(i, len(ours))
    oj += range(j, len(theirs))
    return np.array(mi, int), np.array(mj, int), np.array(oi, int), np.array(oj, int)


@pytest.mark.skipif(not os.environ.get("OCCDATA_DEVKIT_PYTHON"),
                    reason="set OCCDATA_DEVKIT_PYTHON to a python with nuscenes-devkit (scripts/devkit_env.sh)")
def test_lidar_sweeps_match_the_official_devkit_multisweep(synth_root: Path, tmp_path: Path) -> None:
    n = 12  # crosses the previous keyframe: 9 sweeps, keyframe k-1, 2 sweeps before it
    out = tmp_path / "d.zarr"
    code, output = _build(synth_root, out, "--lidar-sweeps", str(n))
    assert code == 0, output
    script = tmp_path / "devkit_multisweep.py"
    script.write_text(DEVKIT_MULTISWEEP)
    res = subprocess.run([os.environ["OCCDATA_DEVKIT_PYTHON"], str(script), str(synth_root), str(n + 1),
                          str(tmp_path / "devkit.npz")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    store = open_store(out)
    worst, total, flips = 0.0, 0, 0
    with np.load(tmp_path / "devkit.npz", allow_pickle=False) as devkit:
        for i in range(store.n_samples):
            for c, uvd in enumerate(store.depth_points(i)):
                key = f"{store.token(i)}/{CAMERA_ORDER[c]}"
                theirs, (w, h) = devkit[key], devkit[key + "/size"]
                ours = uvd[_devkit_rule(uvd, w, h)]
                mi, mj, oi, oj = _match_in_order(ours, theirs)
                # Equal counts, up to points that float32 rounding moves across a border.
                assert _at_border(ours[oi], w, h).all() and _at_border(theirs[oj], w, h).all(), (key, oi, oj)
                assert abs(len(ours) - len(theirs)) <= _at_border(ours, w, h).sum()
                worst = max(worst, float(np.abs(ours[mi, :2] - theirs[mj, :2]).max()))
                # The devkit rounds to float32 in the global frame (synthetic towns lie ~1-4 km out).
                np.testing.assert_allclose(ours[mi, 2], theirs[mj, 2], rtol=0, atol=1e-3)
                total += len(theirs)
                flips += len(oi) + len(oj)
    print(f"\ndevkit multisweep ({n + 1} sweeps): {total} points in image, {flips} border flips, "
          f"max |d uv| {worst:.4f} px")
    assert total > 1_000_000 and worst < 0.05
