"""Flow: per voxel the ground velocity of the box whose points won its vote (the devkit's
`box_velocity`, rotated into the grid's frame); 0 for the static scene and free space."""

from __future__ import annotations

import numpy as np

from occdata.constants import NUM_CLASSES
from occdata.labels.kernels import vote_sources
from occdata.labels.options import LabelSources
from occdata.nuscenes.annotations import BoxRecord

__all__ = ["box_velocities", "voxel_flow"]


def voxel_flow(votes: list[np.ndarray], box_of_vote: list[int], semantics: np.ndarray, v_global: np.ndarray,
               R_grid_from_global: np.ndarray, filled_by: np.ndarray | None = None) -> np.ndarray:
    """`(X, Y, Z, 2) float32` m/s (vx, vy) in the grid's frame: per voxel, the ground velocity
    `v_global (B, 3)` (NaN already 0) of the box whose placed points cast most of the votes for the
    voxel's class (`vote_sources`: ties to the static scene, then to the lower box index); 0 where
    the static scene won and in free space. vz is dropped before rotating: velocity over the ground.
    `filled_by (X, Y, Z)`: the box (index in `v_global`) whose densification filled a voxel, -1 none."""
    flow = np.zeros((semantics.size, 2), np.float32)
    voxel, source = vote_sources(votes, semantics, NUM_CLASSES - 1)
    on_box = source > 0
    v_ground = np.asarray(v_global, np.float64).reshape(-1, 3) * (1.0, 1.0, 0.0)
    v_grid = v_ground @ np.asarray(R_grid_from_global, np.float64).T
    if on_box.any():
        box = np.asarray(box_of_vote, np.int64)[source[on_box] - 1]
        flow[voxel[on_box]] = v_grid[box, :2]
    if filled_by is not None:
        filled = np.flatnonzero(filled_by.reshape(-1) >= 0)
        flow[filled] = v_grid[filled_by.reshape(-1)[filled], :2]
    return flow.reshape(*semantics.shape, 2)


def box_velocities(inputs: LabelSources, keyframe_boxes: list[tuple[BoxRecord, ...]],
                   held: list[tuple[BoxRecord, ...]]) -> list[np.ndarray]:
    """Per keyframe, `v_global (B, 3) float64` m/s of its boxes then its held boxes: the devkit's
    `box_velocity` of each annotated box (NaN, no usable neighbour: 0), 0 for a held (parked) one."""
    by_token = inputs.annotations.box_velocities()
    out = []
    for boxes, parked in zip(keyframe_boxes, held, strict=True):
        v = np.zeros((len(boxes) + len(parked), 3))
        for b, box in enumerate(boxes):
            v[b] = by_token.get(box.token, np.zeros(3))
        out.append(np.nan_to_num(v, nan=0.0))
    return out
