"""The viewer's speed view: occupied voxels coloured by |flow| (no viser needed)."""

from __future__ import annotations

import numpy as np
import pytest

from occdata.constants import FREE_LABEL, GRID
from occdata.errors import OccDataError
from occdata.view.config import FrameOptions, ViewConfig
from occdata.view.frame import compose_frame
from occdata.view.source import SampleData
from occdata.view.voxels import (
    GHOST_COLOR,
    SPEED_BINS,
    SPEED_COLORS,
    STATIC_COLOR,
    layers_from_ids,
    speed_bin_name,
    speed_ids,
)

CAR, ROAD = 4, 11


def _scene() -> tuple[np.ndarray, np.ndarray, dict[tuple[int, int, int], float]]:
    """Isolated car voxels with known speeds (vx, vy chosen so |v| is the speed), a road voxel at rest."""
    lab = np.full(GRID.shape, FREE_LABEL, np.uint8)
    flow = np.zeros((*GRID.shape, 2), np.float32)
    speeds = {(20, 20, 5): 0.0, (40, 20, 5): 0.05, (60, 20, 5): 0.5, (80, 20, 5): 1.5, (100, 20, 5): 2.5,
              (120, 20, 5): 5.5, (140, 20, 5): 8.9, (160, 20, 5): 13.0}
    for ijk, v in speeds.items():
        lab[ijk] = CAR
        flow[ijk] = (0.6 * v, -0.8 * v)
    lab[30, 60, 2] = ROAD
    speeds[(30, 60, 2)] = 0.0
    flow[30, 70, 2] = (50.0, 0.0)  # flow on a free voxel is never drawn
    return lab, flow, speeds


def _layer_of_each_voxel(layers) -> dict[tuple[int, int, int], object]:  # noqa: ANN001
    out = {}
    for layer in layers:
        for c in layer.centers_ego:
            ijk = tuple(np.floor((c - np.asarray(GRID.lower)) / GRID.voxel_size).astype(int).tolist())
            out[ijk] = layer
    return out


def test_speed_colours_follow_the_speeds() -> None:
    lab, flow, speeds = _scene()
    per_voxel = _layer_of_each_voxel(layers_from_ids(speed_ids(lab, flow), speed_view=True))
    assert set(per_voxel) == set(speeds)  # every occupied voxel, nothing free
    for ijk, v in speeds.items():
        layer = per_voxel[ijk]
        k = int(np.searchsorted(SPEED_BINS, np.float32(v), side="right"))  # by hand: the bin whose edges hold v
        assert (layer.color == STATIC_COLOR) == (v < 0.1), (ijk, v)
        if v >= 0.1:
            assert layer.color == SPEED_COLORS[k - 1] and layer.name == f"speed_{k}"
    # faster voxels take later colours of the ramp
    moving = sorted((v, SPEED_COLORS.index(per_voxel[ijk].color)) for ijk, v in speeds.items() if v >= 0.1)
    assert [c for _, c in moving] == sorted(c for _, c in moving) and moving[-1][1] == len(SPEED_COLORS) - 1
    assert per_voxel[(160, 20, 5)].color == SPEED_COLORS[-1] and per_voxel[(60, 20, 5)].color == SPEED_COLORS[0]
    assert per_voxel[(30, 60, 2)].color == STATIC_COLOR and per_voxel[(20, 20, 5)].class_id is None
    assert speed_bin_name(0).startswith("static") and speed_bin_name(len(SPEED_BINS)) == ">= 9 m/s"
    assert speed_bin_name(3) == "2-3 m/s"


def test_speed_view_mask_and_missing_flow() -> None:
    lab, flow, _ = _scene()
    mask = np.zeros(GRID.shape, np.uint8)
    mask[160, 20, 5] = 1
    sample = SampleData(index=0, token="t", scene="s", position=0, n_in_scene=1, semantics=lab,
                        masks={"camera": mask}, pred=None, camera_names=(), cameras=(), flow=flow)
    frame = compose_frame(sample, FrameOptions(view="speed", mask="camera"))
    (group,) = frame.groups
    names = {layer.name: layer for layer in group.layers}
    assert set(names) == {"speed_10", "outside_mask"} and names["outside_mask"].color == GHOST_COLOR
    assert len(names["speed_10"].centers_ego) == 1 and not frame.notes
    no_flow = SampleData(index=0, token="t", scene="s", position=0, n_in_scene=1, semantics=lab, masks={},
                         pred=None, camera_names=(), cameras=())
    frame = compose_frame(no_flow, FrameOptions(view="speed"))
    assert frame.groups == () and "No flow in this store" in frame.notes[0]
    ViewConfig(store="x.zarr", frame=FrameOptions(view="speed"))  # needs no prediction folder
    with pytest.raises(OccDataError):
        FrameOptions(view="velocity")  # type: ignore[arg-type]
