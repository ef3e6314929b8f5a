"""The open-road smear measure (`benchmarks.labels_lyft_smear`) on a hand-made keyframe, and its goal on the
real Lyft keyframes: carving removes >= 80% of naive accumulation's smear, losing <= 1% of hit recall."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_LYFT

from benchmarks.labels_lyft_smear import KeyframeReturns, hit_recall, open_road_band, smear_figures
from occdata.constants import FREE_LABEL, GRID
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.nuscenes import load_nuscenes


def _voxel(x: float, y: float, z: float) -> tuple[int, ...]:
    return tuple(int(v) for v in GRID.index_of(np.array([[x, y, z]]))[0])


def _keyframe() -> KeyframeReturns:
    """A LiDAR at (0, 0, 1.8) over a flat road (z = 0, returns every 0.2 m for x 2-20 m, |y| <= 2 m) and
    a car's side at x = 10.1 m, y = 0.1 m (returns 0.1-1.5 m up)."""
    x, y = np.meshgrid(np.arange(2.0, 20.0, 0.2), np.arange(-2.0, 2.01, 0.2), indexing="ij")
    road = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    car = np.stack([np.full(15, 10.1), np.full(15, 0.1), np.linspace(0.1, 1.5, 15)], axis=1)
    points = np.vstack([road, car])
    return KeyframeReturns(points, np.tile([0.0, 0.0, 1.8], (len(points), 1)))


def test_open_road_band_by_hand() -> None:
    """Column (6.2, -1.0) (voxel [6.0, 6.4] x [-1.2, -0.8]): the road returned, nothing standing.
    Rays to the road at x = 9.3-20 m pass it at 1.8 (1 - 6.2 / x) = 0.6-1.24 m, so its voxels at z
    [0.6, 1.0] and [1.0, 1.4] (0.8 and 1.2 m over the road) are in the band; [1.4, 1.8] (no ray that
    high there: the rays to the car pass y 0-0.1) and [0.2, 0.6] (centre under 0.5 m) are not. The
    car's column is not open road."""
    band, height = open_road_band(_keyframe())
    assert [bool(band[_voxel(6.2, -1.0, z)]) for z in (0.4, 0.8, 1.2, 1.6)] == [False, True, True, False]
    assert height[_voxel(6.2, -1.0, 0.8)] == pytest.approx(0.8, abs=0.01)
    assert not band[_voxel(10.1, 0.1, 0.8)[:2]].any(), "a column with a return 0.1-1.5 m up is not open road"
    assert not band[_voxel(-5.0, 0.0, 0.8)[:2]].any(), "a column no return reached is not measured"


def test_hit_recall_by_hand() -> None:
    """Labels holding only the car's voxels: the returns counted are those whose voxel is one of them
    (tested here return by return against the car's voxels: its 15 and the road returns sharing its
    bottom voxel), out of every return in the grid."""
    ret = _keyframe()
    sem = np.full(GRID.shape, FREE_LABEL, np.uint8)
    car = ret.points[-15:]
    idx = GRID.index_of(car)
    sem[tuple(idx.T)] = 0
    hit, total = hit_recall(ret, sem)
    every = GRID.index_of(ret.points)
    expect = int((every[:, None, :] == idx[None, :, :]).all(axis=2).any(axis=1).sum())
    assert total == len(ret.points) and hit == expect and 15 < hit < 30


@pytest.mark.slow
def test_real_lyft_open_road_smear_goal(tmp_path: Path) -> None:
    """On the real Lyft keyframes carving removes >= 80% of naive accumulation's open-road smear and
    loses <= 1% of hit recall (two `occdata labels` runs and 16 keyframes' rays: ~1-2 min)."""
    if not REAL_LYFT.is_dir():
        pytest.skip("the real Lyft keyframes are not in ../shared/data/lyft-real")
    runs = {"naive": tmp_path / "naive", "carve": tmp_path / "carve"}
    for name, opts in (("naive", LabelOptions(carve=False)), ("carve", LabelOptions())):
        generate_labels(LabelsConfig(root=REAL_LYFT, out=runs[name], options=opts, progress=False))
    rows = smear_figures(load_nuscenes(REAL_LYFT, None).samples, runs)
    naive, carve = rows["naive"], rows["carve"]
    assert naive["smear_total"] > 10_000, "the naive labels must smear the open road for this to mean anything"
    assert carve["smear_total"] <= 0.2 * naive["smear_total"]
    assert carve["hit_recall"] >= naive["hit_recall"] - 0.01
