"""occdata.view.render: hand-built grids drawn where and in the colours expected; the prediction picture's
layout; class colours present exactly where the truth has those classes."""

from __future__ import annotations

import numpy as np
import pytest

from occdata.constants import CLASS_COLORS, FREE_LABEL, GRID
from occdata.view.render import EGO_COLOR, View, bev_top_view, prediction_picture, render_voxels

CAR, BUS, ROAD, MANMADE = 4, 3, 11, 15


def _empty() -> np.ndarray:
    return np.full(GRID.shape, FREE_LABEL, dtype=np.uint8)


def _has_color(img: np.ndarray, rgb: tuple[int, int, int]) -> int:
    return int(np.all(img == np.array(rgb, dtype=np.uint8), axis=-1).sum())


def test_empty_grid_draws_only_ego() -> None:
    img = render_voxels(_empty(), (300, 400))
    assert img.shape == (300, 400, 3) and img.dtype == np.uint8
    colours = {tuple(c) for c in img.reshape(-1, 3)}
    assert (255, 255, 255) in colours
    assert _has_color(img, EGO_COLOR) > 0  # top face of the ego box
    assert _has_color(render_voxels(_empty(), (300, 400), ego=False), (255, 255, 255)) == 300 * 400


def test_block_drawn_in_its_colour_and_place() -> None:
    """A 10x10x2 car block in front-left of the ego: its top face appears in the car colour, in the
    upper-left quadrant of a straight-down view (forward = up, left = left), and nowhere else."""
    sem = _empty()
    sem[150:160, 140:150, 4:6] = CAR  # x = +20..24 m (front), y = +16..20 m (left)
    img = render_voxels(sem, (400, 400), View(azimuth_deg=0.0, elevation_deg=89.9), ego=False)
    ys, xs = np.nonzero(np.all(img == np.array(CLASS_COLORS[CAR], dtype=np.uint8), axis=-1))
    assert len(ys) > 50
    assert ys.max() < 200 and xs.max() < 200  # upper-left quadrant
    # Block spans 4 m of 80 m in each direction: about 1/20 of the fitted grid width.
    assert 0.6 * 400 / 20 < xs.max() - xs.min() + 1 < 1.6 * 400 / 20


def test_occlusion_top_voxel_hides_lower_one() -> None:
    """Seen from straight above, a road slab under a manmade roof shows only the roof where they overlap."""
    sem = _empty()
    sem[90:110, 90:110, 0] = ROAD
    sem[60:80, 60:80, 0] = ROAD
    sem[60:80, 60:80, 8] = MANMADE  # roof over the second slab only
    view = View(azimuth_deg=0.0, elevation_deg=89.9)
    img = render_voxels(sem, (400, 400), view, ego=False)
    roof = np.all(img == np.array(CLASS_COLORS[MANMADE], dtype=np.uint8), axis=-1)
    road = np.all(img == np.array(CLASS_COLORS[ROAD], dtype=np.uint8), axis=-1)
    assert roof.sum() > 100 and road.sum() > 100
    ry, rx = np.nonzero(roof)
    box = road[ry.min() + 2: ry.max() - 1, rx.min() + 2: rx.max() - 1]
    assert box.sum() == 0  # no road pixel inside the roof's footprint


def test_mask_hides_voxels() -> None:
    sem = _empty()
    sem[120:130, 100:110, 3:5] = BUS
    mask = np.zeros(GRID.shape, dtype=np.uint8)
    assert _has_color(render_voxels(sem, (300, 400)), CLASS_COLORS[BUS]) > 0
    assert _has_color(render_voxels(sem, (300, 400), mask=mask), CLASS_COLORS[BUS]) == 0


def test_bev_orientation_and_mask() -> None:
    """x forward is up, y left is left; columns without a visible voxel are greyed."""
    sem = _empty()
    sem[190:200, 190:200, 2] = CAR  # front-left corner of the grid
    sem[0:10, 0:10, 2] = BUS  # back-right corner
    img = bev_top_view(sem, cell_px=1)
    assert img.shape == (200, 200, 3)
    assert tuple(img[3, 3]) == CLASS_COLORS[CAR] and tuple(img[196, 196]) == CLASS_COLORS[BUS]
    mask = np.zeros(GRID.shape, dtype=np.uint8)
    mask[100:, :, :] = 1  # front half visible
    img = bev_top_view(sem, mask, cell_px=1)
    assert tuple(img[3, 3]) == CLASS_COLORS[CAR]  # visible: true colour
    assert tuple(img[196, 196]) != CLASS_COLORS[BUS]  # not visible: greyed
    assert tuple(img[150, 50]) == (185, 185, 185) and tuple(img[50, 50]) == (255, 255, 255)


@pytest.mark.parametrize("with_gt", [True, False])
def test_prediction_picture_layout(with_gt: bool) -> None:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (225, 400, 3), dtype=np.uint8) for _ in range(6)]
    gt = _empty()
    gt[:, :, 0] = ROAD
    gt[120:130, 90:95, 1:4] = CAR
    pred = _empty()
    pred[:, :, 0] = ROAD
    mask = np.ones(GRID.shape, dtype=np.uint8)
    pic = prediction_picture(images, pred, gt if with_gt else None, mask if with_gt else None,
                             camera_names=[f"CAM{i}" for i in range(6)], title="t")
    assert pic.shape[1] == 1600 and pic.dtype == np.uint8
    # rows: title 30 + cameras 2 x (533 * 225 / 400 = 300) + 3D 600 + top views 600 + legend
    assert 30 + 600 + 600 + 600 < pic.shape[0] < 30 + 600 + 600 + 600 + 120
    lower = pic[630:]  # the renderings below the cameras
    third = pic[630:1230]
    assert _has_color(third[:, :800], CLASS_COLORS[ROAD]) > 1000  # prediction panel
    if not with_gt:
        assert _has_color(third, CLASS_COLORS[CAR]) == 0
    else:
        assert _has_color(third[:, 800:], CLASS_COLORS[CAR]) > 0  # truth panel has the car
        assert _has_color(third[:, :800], CLASS_COLORS[CAR]) == 0  # prediction has none
    assert _has_color(lower, CLASS_COLORS[BUS]) == 0  # neither has a bus (legend lists present classes only)
