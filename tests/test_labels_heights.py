"""Height alignment of LiDAR frames (`occdata.labels.heights`): hand-worked ground columns, a sloped
road whose frames were placed at z = 0 (as nuScenes ego poses are) recovered to the centimetre, carving
on that road with and without the alignment, and the real scene-0916 keyframes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from occdata.labels.carve import CarveGrid, CarveOptions
from occdata.labels.heights import HeightOffsets, ground_cells, ground_map, height_offsets


def test_ground_cells_hand_worked() -> None:
    """Column [0, 0.5)^2 holds z = 0, 0.1, 0.15, 0.5, 2.0: the lowest is 0, within 0.2 m of it are 0, 0.1
    and 0.15 (mean 0.0833). Column [1, 1.5) x [0, 0.5) has one point: left out. A point 40 m away is beyond
    the 30 m reach."""
    pts = np.array([[0.1, 0.1, 2.0], [0.2, 0.3, 0.1], [0.4, 0.4, 0.5], [0.3, 0.2, 0.0], [0.1, 0.4, 0.15],
                    [1.2, 0.2, 0.0], [40.0, 0.0, 0.0], [40.1, 0.1, 0.0]])
    keys, z = ground_cells(pts, np.zeros(3))
    assert len(keys) == 1
    np.testing.assert_allclose(z, [0.25 / 3])


def _sloped_road(slope: float, xs: np.ndarray, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Frames of a road z = slope * x, the LiDAR 1.8 m over it at each x in `xs`, every frame placed at
    z = 0 as nuScenes poses are: `(origin (3,), points (N, 3))` in that frame's (wrong) global heights.
    Each frame sees the road within 30 m and a box of clutter (a car's roof, 1.5 m up) at x + 8."""
    rng = np.random.default_rng(seed)
    frames = []
    for x0 in xs:
        road = np.column_stack([rng.uniform(x0 - 30, x0 + 30, 6000), rng.uniform(-6, 6, 6000)])
        road = road[np.hypot(road[:, 0] - x0, road[:, 1]) <= 30]
        z = slope * road[:, 0] + rng.normal(0, 0.02, len(road))
        car = np.column_stack([rng.uniform(x0 + 7, x0 + 9, 300), rng.uniform(-1, 1, 300),
                               slope * (x0 + 8) + 1.5 + rng.normal(0, 0.02, 300)])
        pts = np.vstack([np.column_stack([road, z]), car])
        pts[:, 2] -= slope * x0  # the pose says z = 0: the frame's heights are relative to its own road
        frames.append((np.array([x0, 0.0, 1.8]), pts))
    return frames


def test_offsets_recover_a_sloped_road() -> None:
    """Frames 4 m apart on a 3% road: frame k's heights are low by 0.03 x_k. The fitted offsets equal
    that up to a common constant, within 1 cm (the truth is the slope we built, not the fit)."""
    xs = np.arange(0.0, 61.0, 4.0)
    frames = _sloped_road(0.03, xs)
    cells = [ground_cells(p, o) for o, p in frames]
    fit = height_offsets(cells, np.array([o for o, _ in frames]), (xs * 1e5).astype(np.int64))
    truth = -0.03 * xs
    err = (fit.dz - fit.dz.mean()) - (truth - truth.mean())
    assert np.abs(err).max() < 0.01, err
    assert fit.at(int(2e5)) == pytest.approx((fit.dz[0] + fit.dz[1]) / 2), "between two frames: interpolated"


def test_offsets_of_a_flat_road_are_zero() -> None:
    xs = np.arange(0.0, 41.0, 4.0)
    frames = _sloped_road(0.0, xs)
    fit = height_offsets([ground_cells(p, o) for o, p in frames], np.array([o for o, _ in frames]),
                         (xs * 1e5).astype(np.int64))
    assert np.abs(fit.dz).max() < 0.005


def test_alignment_keeps_a_sloped_road_static() -> None:
    """On the 3% road placed at z = 0, the later frames' rays pass through the ground that earlier
    frames put higher: without alignment 23% of the road points are taken for movers (measured); with
    the fitted offsets none is. The car driving 8 m ahead of the LiDAR moves: dynamic either way (87%)."""
    xs = np.arange(0.0, 61.0, 4.0)
    frames = _sloped_road(0.03, xs, seed=1)
    times = (xs * 1e5).astype(np.int64)
    fit = height_offsets([ground_cells(p, o) for o, p in frames], np.array([o for o, _ in frames]), times)
    lo, hi = np.array([-35.0, -8.0, -3.0]), np.array([95.0, 8.0, 4.0])
    shares, car = {}, {}
    for name, heights in (("raw", None), ("aligned", fit)):
        g = CarveGrid(lo, hi, CarveOptions(), heights)
        for s, ((o, p), t) in enumerate(zip(frames, times, strict=True)):
            g.add_slot(s, [(o, p)], t_us=int(t))
        pairs = [(p, int(t)) for (_, p), t in zip(frames, times, strict=True)]
        shares[name] = np.mean(np.concatenate([g.dynamic(p[:-300], t) for p, t in pairs]))
        car[name] = np.mean(np.concatenate([g.dynamic(p[-300:], t) for p, t in pairs]))
    assert shares["raw"] > 0.1, shares
    assert shares["aligned"] < 0.005, shares
    assert min(car.values()) > 0.7, car


def test_height_offsets_validated() -> None:
    with pytest.raises(ValueError, match="increasing"):
        HeightOffsets(np.array([2, 1]), np.zeros(2))
    with pytest.raises(ValueError, match="one time per offset"):
        HeightOffsets(np.array([1]), np.zeros(2))


def test_ground_map_is_the_lowest_aligned_surface() -> None:
    """Slot 0 saw column 0 at 0.30 m (a car's floor hid the road) and column 1 at 0.05 m; slot 1, whose
    heights are 0.1 m high (dz = 0.1), saw column 0 at 0.12 m: the road there is at 0.02 m. Column 2 was
    never seen: NaN."""
    key = lambda i: np.int64(i) * (1 << 31)  # noqa: E731 - column (i, 0), as ground_cells packs it
    cells = [(np.array([key(0), key(1)]), np.array([0.30, 0.05])), (np.array([key(0)]), np.array([0.12]))]
    g = ground_map(cells, np.array([0.0, 0.1]))
    under = g.height_under(np.array([[0.2, 0.2, 5.0], [0.7, 0.1, 0.0], [1.2, 0.1, 0.0]]))
    np.testing.assert_allclose(under[:2], [0.02, 0.05])
    assert np.isnan(under[2])


def test_points_just_over_the_ground_stay_static() -> None:
    """Rays from 1.8 m to the ground 25 m off, which lies 0.15 m lower than the road at x = 20 (a dip),
    pass 0.24-0.26 m over the road at x = 20-20.2 (graze 0.3 m: only their last 3.9 m are cut): in the
    0.3 m voxel [0, 0.3] of a road point at 0.02 m. Without the ground rule that point is dynamic; with
    `ground_clearance` 0.3 it is static. A car's point 0.75 m up, which rays to a wall at 30 m pass
    through, stays dynamic either way."""
    origin = np.array([0.0, 0.0, 1.8])
    road, car = np.array([[20.1, 0.0, 0.02]]), np.array([[20.1, 0.45, 0.75]])
    later = np.array([[25.0, 0.0, -0.13], [25.0, 0.5, -0.13], [30.0, 0.672, 0.233]])
    ground = ground_map([(ground_cells(np.vstack([road, road + [0.01, 0.0, 0.0]]), origin)[0], np.array([0.02]))],
                        np.zeros(1))
    for clearance, expect in ((0.0, True), (0.3, False)):
        opts = CarveOptions(voxel_size=0.3, ground_clearance=clearance)
        g = CarveGrid(np.array([-1.0, -1.0, -0.6]), np.array([31.0, 1.0, 2.4]), opts, None, ground)
        g.add_slot(0, [(origin, np.vstack([road, car]))])
        g.add_slot(1, [(origin, later)])
        g.add_slot(2, [(origin, later)])
        assert g.dynamic(road).tolist() == [expect], clearance
        assert g.dynamic(car).tolist() == [True], clearance


def test_real_scene_keyframes_agree_in_height_once_aligned(real_seq_root: Path) -> None:
    """Real scene-0916 (41 keyframes, poses at z = 0): keyframes 10-40 m apart disagree by about a third
    of a metre about the ground both saw (measured: 0.33-0.37 m median); after the fitted offsets, by
    about 2-3 cm. Each pair's disagreement is the median over their shared ground columns."""
    from occdata.labels.frames import frame_points
    from occdata.nuscenes import load_nuscenes

    ds = load_nuscenes(real_seq_root, None)
    recs = sorted((s.lidar for s in ds.samples), key=lambda r: r.timestamp)
    clouds = [frame_points(r) for r in recs]
    cells = [ground_cells(p[off], o) for p, o, off in clouds]
    origins = np.array([o for _, o, _ in clouds])
    fit = height_offsets(cells, origins, [r.timestamp for r in recs])
    raw, aligned = [], []
    for i in range(len(cells)):
        for j in range(i + 1, len(cells)):
            if not 10 <= np.hypot(*(origins[j][:2] - origins[i][:2])) <= 40:
                continue
            _, a, b = np.intersect1d(cells[i][0], cells[j][0], assume_unique=True, return_indices=True)
            if len(a) >= 20:
                d = float(np.median(cells[j][1][b] - cells[i][1][a]))
                raw.append(abs(d))
                aligned.append(abs(d - (fit.dz[j] - fit.dz[i])))
    assert len(raw) > 100
    assert np.median(raw) > 0.25, np.median(raw)
    assert np.median(aligned) < 0.05, np.median(aligned)
    assert np.ptp(fit.dz) > 1.0, "the road climbs and falls over a metre along the scene"
