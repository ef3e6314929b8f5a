"""Motion inside a sweep (`occdata.labels.deskew`): an uncompensated spin from a truck on a curve, made
from an analytic trajectory (the truth), placed back by poses sampled at 20 Hz; through a `.pcd` file
with a `timestamp` field and `frame_points`; and per-point times that are not microseconds."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from occdata.errors import OccDataError
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.deskew import PoseTrack, deskew_points
from occdata.labels.frames import frame_points
from occdata.nuscenes import LidarRecord

SPEED, YAW_RATE = 22.0, 0.3  # m/s, rad/s: a truck on a 73 m radius curve
T_REF = 1_700_000_000_000_000  # us
T_EGO_FROM_LIDAR = np.array([[0.0, -1.0, 0.0, 1.2], [1.0, 0.0, 0.0, 0.1], [0.0, 0.0, 1.0, 2.5], [0, 0, 0, 1]])


def _T_global_from_ego(t_us: float) -> np.ndarray:
    """The analytic pose at `t_us`: a circular arc at constant speed and yaw rate (the truth)."""
    s = (t_us - T_REF) * 1e-6
    yaw = YAW_RATE * s
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:3, 3] = [SPEED / YAW_RATE * np.sin(yaw) + 100.0, SPEED / YAW_RATE * (1 - np.cos(yaw)) - 50.0, 0.0]
    return T


def _track(period_us: int = 50_000) -> PoseTrack:
    return PoseTrack.of((t, _T_global_from_ego(t)) for t in range(T_REF - 500_000, T_REF + 500_001, period_us))


def _spin(n: int = 3000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static world points `(N, 3)` around the truck, their firing times over a 100 ms spin, and the
    points as an uncompensated LiDAR reports them: each in the LiDAR frame of its own time."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(5.0, 40.0, n), rng.uniform(-np.pi, np.pi, n)
    ego = _T_global_from_ego(T_REF)
    world = transform_points(ego, np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.0, 3.0, n)], 1))
    times = (T_REF + (a / np.pi) * 50_000).astype(np.int64)  # the azimuth sets the firing time
    lidar = np.stack([transform_points(invert_rigid(_T_global_from_ego(t) @ T_EGO_FROM_LIDAR), p[None])[0]
                      for t, p in zip(times, world, strict=True)])
    return world, times, lidar


def test_pose_track_interpolates_and_extrapolates() -> None:
    track = _track()
    np.testing.assert_allclose(track.at(track.t_us), track.T_global_from_ego, atol=1e-9)
    mid = track.at(np.array([T_REF + 25_000]))[0]
    np.testing.assert_allclose(mid, _T_global_from_ego(T_REF + 25_000), atol=3e-3)  # chord vs arc: 2.1 mm
    # 50 ms past the last pose (a scene's last spin): the last segment's motion carried on, the chord's
    # heading off the curve's by 0.3 rad/s x 50 ms: 1.7 cm
    np.testing.assert_allclose(track.at(np.array([T_REF + 550_000]))[0], _T_global_from_ego(T_REF + 550_000),
                               atol=0.025)
    assert np.abs(track.T_global_from_ego[-1] - _T_global_from_ego(T_REF + 550_000)).max() > 1.0  # held: 1.1 m off
    single = PoseTrack.of([(T_REF, np.eye(4))])
    np.testing.assert_allclose(single.at(np.array([T_REF + 10]))[0], np.eye(4))
    with pytest.raises(ValueError, match="increase"):
        PoseTrack(np.array([2, 1]), np.stack([np.eye(4)] * 2))


def test_deskew_places_an_uncompensated_spin_where_it_was() -> None:
    """Placed by the sweep's pose alone the points are up to ~1.1 m off (22 m/s x 50 ms); placed by the
    interpolated pose of each point's time they land within 5 mm of the truth."""
    world, times, lidar = _spin()
    ego = _T_global_from_ego(T_REF)
    naive = transform_points(ego @ T_EGO_FROM_LIDAR, lidar)
    assert np.linalg.norm(naive - world, axis=1).max() > 1.0
    fixed = transform_points(ego, deskew_points(lidar, times, T_REF, T_EGO_FROM_LIDAR, ego, _track()))
    assert np.linalg.norm(fixed - world, axis=1).max() < 0.005
    # a sweep whose points share its timestamp is left as it was
    same = deskew_points(lidar, np.full(len(lidar), T_REF), T_REF, T_EGO_FROM_LIDAR, ego, _track())
    np.testing.assert_allclose(same, transform_points(T_EGO_FROM_LIDAR, lidar), atol=1e-6)


def _pcd(path: Path, lidar: np.ndarray, times: np.ndarray) -> None:
    import pypcd4

    cols = [*(lidar[:, k].astype(np.float32) for k in range(3)), np.zeros(len(lidar), np.float32),
            times.astype(np.uint64)]
    pc = pypcd4.PointCloud.from_points(cols, ("x", "y", "z", "intensity", "timestamp"),
                                       (np.float32,) * 4 + (np.uint64,))
    buf = io.BytesIO()
    pc.save(buf, encoding=pypcd4.Encoding.BINARY)
    path.write_bytes(buf.getvalue())


def test_frame_points_deskews_a_pcd_with_point_times(tmp_path: Path) -> None:
    world, times, lidar = _spin(seed=1)
    _pcd(tmp_path / "sweep.pcd", lidar, times)
    rec = LidarRecord("LIDAR_LEFT", "sd", tmp_path / "sweep.pcd", T_EGO_FROM_LIDAR, _T_global_from_ego(T_REF), T_REF)
    fixed, origin, off_ego = frame_points(rec, _track())
    assert off_ego.all()
    assert np.linalg.norm(fixed - world, axis=1).max() < 0.01  # float32 file coordinates: ~mm
    plain, _, _ = frame_points(rec)  # no track: the sweep's pose for every point, as before
    assert np.linalg.norm(plain - world, axis=1).max() > 1.0
    np.testing.assert_allclose(origin, (_T_global_from_ego(T_REF) @ T_EGO_FROM_LIDAR)[:3, 3])


def test_point_times_that_are_not_microseconds_are_refused(tmp_path: Path) -> None:
    _, times, lidar = _spin(n=50)
    _pcd(tmp_path / "s.pcd", lidar, times // 1000)  # milliseconds
    rec = LidarRecord("LIDAR_LEFT", "sd", tmp_path / "s.pcd", T_EGO_FROM_LIDAR, _T_global_from_ego(T_REF), T_REF)
    with pytest.raises(OccDataError, match="s.pcd: per-point timestamp .* not microseconds"):
        frame_points(rec, _track())


def test_uncompensated_synth_needs_point_times(tmp_path: Path) -> None:
    from occdata.synth import SynthConfig, synthesize

    with pytest.raises(OccDataError, match="--uncompensated needs per-point times"):
        synthesize(SynthConfig(out=tmp_path / "w", scenes=1, samples=1, rig="nuscenes", uncompensated=True))


@pytest.mark.slow
def test_deskew_on_an_uncompensated_synthetic_truck(tmp_path: Path) -> None:
    """`occdata synth --rig truckscenes --uncompensated`: every sweep spins over 100 ms, each point from
    the ego pose of its time. Labelled by sweep poses alone, static surfaces smear (precision ~0.94 at
    the world's 7.5 m/s); with --deskew the labels are as precise as the same world's compensated ones
    (~0.9997, the truth being the world's own voxelisation)."""
    from click.testing import CliRunner

    from cli.occdata_cli import main
    from occdata.labels.score import score_tree
    from occdata.nuscenes.pointfiles import read_pcd
    from occdata.synth import SynthConfig, synthesize

    world = tmp_path / "world"
    synthesize(SynthConfig(out=world, scenes=1, samples=2, seed=3, width=96, height=54, progress=False,
                           rig="truckscenes", uncompensated=True))
    times = read_pcd(next((world / "samples" / "LIDAR_LEFT").glob("*.pcd"))).timestamps.astype(np.int64)
    assert 90_000 <= times.max() - times.min() <= 100_000
    precision = {}
    for name, flag in (("plain", []), ("deskew", ["--deskew"])):
        res = CliRunner().invoke(main, ["labels", "--no-progress", "--root", str(world), "--out", str(tmp_path / name),
                                        *flag])
        assert res.exit_code == 0, res.output
        precision[name] = score_tree(world, tmp_path / name, world / "gts").voxels.precision
    assert precision["deskew"] >= 0.995 and precision["plain"] <= precision["deskew"] - 0.02, precision
    assert json.loads((tmp_path / "deskew" / "labels.json").read_text())["options"]["deskew"] is True
    assert "deskew" not in json.loads((tmp_path / "plain" / "labels.json").read_text())["options"]
