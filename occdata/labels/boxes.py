"""Box membership: which points belong to which annotated object, and which boxes hold at a frame's time.

A point inside a box of its frame's time (the devkit's interpolated boxes, grown by a margin: LiDAR
returns lie on the surface) belongs to the box's instance; ground, buildings and vegetation (by
lidarseg), or without lidarseg the points near a box's floor, stay static. A parked instance is held
at its nearest annotated pose where its annotation stops (`held_static`).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from occdata.errors import OccDataError
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.kernels import points_in_boxes
from occdata.labels.options import LabelOptions, LabelSources
from occdata.nuscenes import LidarRecord
from occdata.nuscenes.annotations import BoxRecord, boxes_for_lidar, moving_instances
from occdata.nuscenes.lidarseg import DROP, OCC3D_FROM_LIDARSEG
from occdata.visibility import GROUND_CLASSES

__all__ = ["STUFF", "box_class", "frame_boxes", "held_static", "in_boxes", "members", "to_box"]

# Occ3D classes that are never an object's own points (ground, buildings, vegetation).
STUFF = np.array(sorted({*GROUND_CLASSES, 15, 16}), np.uint8)


def box_class(box: BoxRecord) -> int:
    """Occ3D class of a box's category (a category outside the 32 nuScenes ones: `others`)."""
    c = OCC3D_FROM_LIDARSEG.get(box.category, 0)
    return 0 if c == DROP else int(c)


def _box_frames(boxes: tuple[BoxRecord, ...], margin: float) -> tuple[np.ndarray, np.ndarray]:
    """`T_box_from_global (B, 4, 4)` and membership half extents `(B, 3)`: length/2, width/2 and
    height/2 grown by `margin`, the floor shifted down by nothing (the grown box is re-centred so
    that its bottom stays at the box's floor)."""
    T = np.zeros((len(boxes), 4, 4))
    half = np.zeros((len(boxes), 3))
    for b, box in enumerate(boxes):
        T_global_from_box = box.T_global_from_box()
        # Shift the box frame up by margin/2 so that growing z by margin/2 each way keeps the floor.
        shift = np.eye(4)
        shift[2, 3] = margin / 2
        T[b] = invert_rigid(T_global_from_box @ shift)
        w, length, h = box.size_wlh
        half[b] = (length / 2 + margin, w / 2 + margin, h / 2 + margin / 2)
    return T, half


def to_box(box: BoxRecord, points: np.ndarray) -> np.ndarray:
    """Global points `(N, 3)` in `box`'s frame, `(N, 3) float64`."""
    return transform_points(invert_rigid(box.T_global_from_box()), points)


def in_boxes(points: np.ndarray, boxes: tuple[BoxRecord, ...], opts: LabelOptions) -> np.ndarray:
    """`(N,) int32` index of the (margin-grown) box holding each global point `(N, 3)`, or -1."""
    if not boxes:
        return np.full(len(points), -1, np.int32)
    T, half = _box_frames(boxes, opts.box_margin)
    return points_in_boxes(np.ascontiguousarray(points), T, half)


def members(points: np.ndarray, cls: np.ndarray | None, boxes: tuple[BoxRecord, ...],
            opts: LabelOptions) -> np.ndarray:
    """`(N,) int32` box index of each global point `(N, 3)`, or -1 for static. With classes, ground,
    building and vegetation points in a box stay static; without, points near a box's floor do."""
    idx = in_boxes(points, boxes, opts)
    if cls is not None:
        idx[np.isin(cls, STUFF)] = -1
        return idx
    for b in np.unique(idx[idx >= 0]):
        sel = np.flatnonzero(idx == b)
        z_box = to_box(boxes[b], points[sel])[:, 2]
        idx[sel[z_box < -boxes[b].size_wlh[2] / 2 + opts.floor_margin]] = -1
    return idx


def frame_boxes(inputs: LabelSources, sample_index: int, k: int, rec: LidarRecord) -> tuple[BoxRecord, ...]:
    """The boxes at frame `rec`'s time, of LiDAR `k` (rig order) of sample `sample_index`: the devkit's
    `get_boxes` for the reference LiDAR (`boxes_for_lidar`); for another LiDAR the same rule, its
    keyframe taking the sample's boxes and a sweep interpolated between the sample it is filed under
    and that sample's `prev`."""
    ds = inputs.dataset
    if k == 0:
        return boxes_for_lidar(inputs.annotations, ds, sample_index, rec)
    sample = ds.samples[sample_index]
    if rec is sample.lidars[k]:
        return inputs.annotations.boxes_at(sample.token, "", 0, 0, rec.timestamp)
    try:
        owner = ds.sample(rec.sample_token or sample.token)
        prev = ds.sample(owner.prev) if owner.prev else None
    except KeyError as exc:
        raise OccDataError(f"sample_data {rec.token!r}: sample {exc.args[0]!r} is not in the dataset") from None
    if prev is None:
        return inputs.annotations.boxes_at(owner.token, "", 0, 0, rec.timestamp)
    return inputs.annotations.boxes_at(owner.token, prev.token, prev.timestamp, owner.timestamp, rec.timestamp)


def held_static(keyframe_boxes: list[tuple[BoxRecord, ...]], travel: float) -> list[tuple[BoxRecord, ...]]:
    """Per keyframe, the boxes of parked instances (not `moving_instances(..., travel)`) that have no
    box there: each instance's box at its nearest annotated keyframe."""
    track: dict[str, list[tuple[int, BoxRecord]]] = defaultdict(list)
    for k, boxes in enumerate(keyframe_boxes):
        for b in boxes:
            track[b.instance_token].append((k, b))
    out: list[list[BoxRecord]] = [[] for _ in keyframe_boxes]
    moving = moving_instances(keyframe_boxes, travel) if travel > 0 else set(track)
    for instance, items in track.items():
        if instance in moving:
            continue
        seen = np.array([k for k, _ in items])
        for k in range(len(keyframe_boxes)):
            if k not in seen:
                out[k].append(items[int(np.argmin(np.abs(seen - k)))][1])
    return [tuple(b) for b in out]
