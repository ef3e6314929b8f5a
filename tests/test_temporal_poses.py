"""The temporal poses on real motion: scene-0916 (41 real keyframes, ../shared/data/nuscenes-real-seq).

Frame t-k's LiDAR points (k = 1..4) are moved into frame t's key ego with the store's poses, as the
loader hands them to the model (`Batch.T_global_from_keyego`, float32) and with the transform the
temporal queue warps by (`T_curaug_from_prevaug`, no BEV augmentation). Static structure must land on
frame t's; the control is the inverse transform (motion applied the wrong way). The same is checked
for `warp_bev` itself on a BEV occupancy raster of the points. `python tests/test_temporal_poses.py`
prints the figures quoted in docs/model.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REAL_SEQ as SEQ
from conftest import missing_fixture

from fastocc.data import BevAugConfig, ImageAugConfig, SampleConfig
from fastocc.data.dataset import load_batch
from fastocc.model.config import COARSE_GRID
from fastocc.model.temporal import T_curaug_from_prevaug, warp_bev
from occdata.nuscenes.reader import load_lidar_points, load_nuscenes
from occdata.store.build import BuildConfig, build_store
from occdata.store.reader import open_store

FRAMES = range(4, 41, 4)  # t; each with k = 1..4 previous frames
EYE = torch.eye(4)


def _static_points_keyego(path: Path, T_ego_from_lidar: np.ndarray) -> torch.Tensor:
    """LiDAR sweep -> key ego (the ego at the LiDAR keyframe): points `(N, 3) float32` above the ground
    (0.5-4 m), inside the 80 m x 80 m grid, beyond 3 m (no hits on the car itself)."""
    p = load_lidar_points(path)[:, :3].astype(np.float64)
    p = p @ T_ego_from_lidar[:3, :3].T + T_ego_from_lidar[:3, 3]
    r = np.hypot(p[:, 0], p[:, 1])
    keep = (p[:, 2] > 0.5) & (p[:, 2] < 4.0) & (np.abs(p[:, :2]) < 40.0).all(1) & (r > 3.0)
    return torch.tensor(p[keep], dtype=torch.float32)


def _load_scene(tmp: Path) -> tuple[torch.Tensor, list[torch.Tensor], np.ndarray, list[np.ndarray]]:
    """Store poses `(41, 4, 4) float32` as the loader yields them, points per frame, float64 store poses,
    and the LiDAR keyframe ego poses of the nuScenes tables."""
    if not SEQ.is_dir():
        missing_fixture("real nuScenes scene", SEQ)
    store = tmp / "seq.zarr"
    build_store(BuildConfig(root=SEQ, out=store, progress=False))
    reader = open_store(store)
    n = reader.n_samples
    test = SampleConfig(image=ImageAugConfig(height=32, width=96, train=False), bev=BevAugConfig(train=False))
    poses = load_batch(store, list(range(n)), test).T_global_from_keyego
    records = {s.token: s for s in load_nuscenes(SEQ).samples}
    lidar = [records[reader.token(i)].lidar for i in range(n)]
    points = [_static_points_keyego(rec.path, rec.T_ego_from_lidar) for rec in lidar]
    return poses, points, reader.small("pose/T_global_from_keyego"), [rec.T_global_from_ego for rec in lidar]


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory):
    return _load_scene(tmp_path_factory.mktemp("seq"))


def _median_nn(a: torch.Tensor, b: torch.Tensor) -> float:
    """Median over the points of `a` of the distance to the nearest point of `b` (brute force, chunked)."""
    return float(torch.cat([torch.cdist(c, b).min(1).values for c in a.split(1000)]).median())


def _moved(points: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    return points @ T[:3, :3].T + T[:3, 3]


def _bev_occupancy(points: torch.Tensor) -> torch.Tensor:
    """Points in key ego -> `(1, 1, 100, 100)` occupancy on the coarse BEV grid (0.8 m cells)."""
    lo, size = torch.tensor(COARSE_GRID.lower[:2]), COARSE_GRID.voxel_size
    ij = torch.floor((points[:, :2] - lo) / size).long()
    ok = ((ij >= 0) & (ij < 100)).all(1)
    occ = torch.zeros(100, 100)
    occ[ij[ok, 0], ij[ok, 1]] = 1.0
    return occ[None, None]


def alignment(scene) -> dict[str, np.ndarray]:
    """Per (t in FRAMES, k = 1..4), arrays `(len(FRAMES), 4)`: median nearest-neighbour distance (m) of
    frame t-k's points moved into frame t (aligned / inverse control / not moved), and the fraction of
    `warp_bev`'s warped occupancy that lands on frame t's occupied cells (aligned / inverse control)."""
    poses, points, _, _ = scene
    gen = torch.Generator().manual_seed(0)
    out = {key: np.zeros((len(FRAMES), 4)) for key in ("nn", "nn_control", "nn_unmoved", "hit", "hit_control")}
    for a, t in enumerate(FRAMES):
        cur = _bev_occupancy(points[t])[0, 0]
        for k in range(1, 5):
            T = T_curaug_from_prevaug(poses[t], EYE, poses[t - k], EYE)  # prev key ego -> current key ego
            prev = points[t - k][torch.randperm(len(points[t - k]), generator=gen)[:2000]]
            out["nn"][a, k - 1] = _median_nn(_moved(prev, T), points[t])
            out["nn_control"][a, k - 1] = _median_nn(_moved(prev, torch.linalg.inv(T)), points[t])
            out["nn_unmoved"][a, k - 1] = _median_nn(prev, points[t])
            occ_prev = _bev_occupancy(points[t - k])
            for key, M in (("hit", T), ("hit_control", torch.linalg.inv(T))):
                warped = warp_bev(occ_prev, M[None], COARSE_GRID)[0, 0]
                out[key][a, k - 1] = float((warped * cur).sum() / warped.sum())
    return out


@pytest.fixture(scope="module")
def measured(scene) -> dict[str, np.ndarray]:
    return alignment(scene)


def test_store_poses_are_the_lidar_keyframe_ego_poses(scene) -> None:
    poses32, _, poses64, lidar_poses = scene
    assert len(poses64) == 41
    np.testing.assert_allclose(poses64, np.stack(lidar_poses), rtol=0, atol=1e-9)
    # The car really moves (about 2 m per keyframe) and turns (over 60 degrees in the scene).
    steps = np.linalg.norm(np.diff(poses64[:, :3, 3], axis=0), axis=1)
    assert 1.5 < steps.min() and steps.max() < 3.5
    yaw = np.unwrap(np.arctan2(poses64[:, 1, 0], poses64[:, 0, 0]))
    assert np.degrees(np.ptp(yaw)) > 60
    # The loader's float32 poses (global coordinates ~1.8 km) give relative transforms within 5 mm.
    for t in FRAMES:
        for k in range(1, 5):
            exact = np.linalg.inv(poses64[t]) @ poses64[t - k]
            used = T_curaug_from_prevaug(poses32[t], EYE, poses32[t - k], EYE).double().numpy()
            assert np.abs(used[:3, 3] - exact[:3, 3]).max() < 5e-3
            assert np.abs(used[:3, :3] - exact[:3, :3]).max() < 1e-4


def test_previous_lidar_moved_into_the_current_key_ego_lines_up(measured) -> None:
    nn, control = measured["nn"], measured["nn_control"]
    # Measured (docs/model.md): aligned 0.13-0.48 m, control 0.81-3.02 m, per-frame ratio >= 3.4.
    assert nn.max() < 0.6
    assert (control / nn).min() > 2.5
    assert np.median(nn) < 0.35 and np.median(control) > 1.0


def test_warp_bev_moves_previous_occupancy_onto_the_current(measured) -> None:
    hit, control = measured["hit"], measured["hit_control"]
    # Measured (docs/model.md): 0.47-0.66 of the warped occupancy lands on occupied cells, control 0.08-0.29.
    assert hit.min() > 0.42
    assert (hit - control).min() > 0.2


if __name__ == "__main__":  # the figures for docs/model.md
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        res = alignment(_load_scene(Path(tmp)))
    print(f"t in {list(FRAMES)}; per k = 1..4: median over t [min, max]")
    for key, arr in res.items():
        cells = ", ".join(f"{np.median(a):.2f} [{a.min():.2f}, {a.max():.2f}]" for a in arr.T)
        print(f"{key:12s} {cells}")
    print(f"nn control / aligned, smallest per frame: {(res['nn_control'] / res['nn']).min():.2f}")
