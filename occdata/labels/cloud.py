"""A scene's points gathered over time, with their classes (class transfer).

A frame's points are split into static ones (global frame), each instance's (its box frame, so that a
moving object accumulates without smearing) and, with carving, dynamic ones (global, kept with their
frame's time). Classes: keyframe points take their lidarseg class (32 -> Occ3D 16 + others; noise and
ego dropped); sweep points take the class of the nearest labelled keyframe point (the same instance's
points in the box frame, or the static points in global). Without lidarseg a box point takes its box's
category and a static point `static_class`, a dynamic one `dynamic_class`.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from occdata.labels.boxes import STUFF, box_class, in_boxes, members, to_box
from occdata.labels.kernels import NO_LABEL, NearestIndex
from occdata.labels.options import LabelOptions, LabelSources, SceneCounts
from occdata.nuscenes import LidarRecord
from occdata.nuscenes.annotations import BoxRecord
from occdata.nuscenes.lidarseg import read_lidarseg

__all__ = ["Cloud", "add_keyframe", "add_sweep", "keyframe_classes"]


@dataclass
class Cloud:
    """Points gathered over a scene: static ones in global, object ones per instance in its box frame,
    dynamic ones (carving) in global with their frame's time."""

    static_pts: list[np.ndarray] = field(default_factory=list)
    static_cls: list[np.ndarray] = field(default_factory=list)
    obj_pts: dict[str, list[np.ndarray]] = field(default_factory=lambda: defaultdict(list))
    obj_cls: dict[str, list[np.ndarray]] = field(default_factory=lambda: defaultdict(list))
    dyn: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # (timestamp us, points, classes)

    def add_dynamic(self, t_us: int, pts: np.ndarray, cls: np.ndarray) -> None:
        if len(pts):
            self.dyn.append((t_us, pts, cls))

    def dynamic_at(self, t_us: int, window_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The dynamic points `(N, 3)` (global) and classes of the frames within `window_s` of `t_us`."""
        near = [(p, c) for t, p, c in self.dyn if abs(t - t_us) <= window_s * 1e6]
        return _cat([p for p, _ in near], [c for _, c in near])

    def dynamic(self) -> tuple[np.ndarray, np.ndarray]:
        """Every frame's dynamic points `(N, 3)` (global) and classes."""
        return _cat([p for _, p, _ in self.dyn], [c for _, _, c in self.dyn])

    def add_static(self, pts: np.ndarray, cls: np.ndarray) -> None:
        self.static_pts.append(pts)
        self.static_cls.append(cls)

    def add_object(self, inst: str, pts: np.ndarray, cls: np.ndarray) -> None:
        self.obj_pts[inst].append(pts)
        self.obj_cls[inst].append(cls)

    def static(self) -> tuple[np.ndarray, np.ndarray]:
        return _cat(self.static_pts, self.static_cls)

    def instance(self, inst: str) -> tuple[np.ndarray, np.ndarray]:
        return _cat(self.obj_pts.get(inst, []), self.obj_cls.get(inst, []))


def _cat(pts: list[np.ndarray], cls: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.uint8)
    return np.concatenate(pts), np.concatenate(cls)


def keyframe_classes(inputs: LabelSources, rec: LidarRecord, n_points: int) -> np.ndarray | None:
    """`(N,) uint8` Occ3D classes (DROP for noise / ego) of a keyframe's points from lidarseg, or None."""
    path = inputs.lidarseg.get(rec.token)
    if path is None or inputs.lidarseg_lut is None:
        return None
    return inputs.lidarseg_lut[read_lidarseg(path, n_points)]


def add_keyframe(cloud: Cloud, points: np.ndarray, cls: np.ndarray | None, boxes: tuple[BoxRecord, ...],
                 opts: LabelOptions, counts: SceneCounts, dynamic: np.ndarray | None = None, t_us: int = 0,
                 own: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Split a keyframe's global points into static and per-instance (box frame) points with classes;
    with `dynamic (N,) bool` (carving) the points outside boxes marked there, less ground, buildings and
    vegetation by lidarseg, are kept as frame `t_us`'s dynamic points instead of static ones. `own`
    (without lidarseg): each point's class if static and if dynamic, `(N,) uint8` each
    (`occdata.labels.semantics.SceneClasses.of`; None: `static_class` and `dynamic_class`)."""
    idx = members(points, cls, boxes, opts)
    for b in np.unique(idx[idx >= 0]):
        sel = idx == b
        box = boxes[b]
        c = cls[sel] if cls is not None else np.full(int(sel.sum()), box_class(box), np.uint8)
        if opts.use_boxes:
            p_box = to_box(box, points[sel])
            cloud.add_object(box.instance_token, p_box, c)
        else:  # the control: the box gives the class only, the point stays where it was seen
            cloud.add_static(points[sel], c)
    static = idx < 0
    if dynamic is not None:
        moving = static & dynamic & (True if cls is None else ~np.isin(cls, STUFF))
        c = cls[moving] if cls is not None else own[1][moving] if own is not None else \
            np.full(int(moving.sum()), opts.dynamic_class, np.uint8)
        cloud.add_dynamic(t_us, points[moving], c)
        counts.dynamic_points += int(moving.sum())
        idx = np.where(moving, -2, idx)  # neither static nor an instance's
        static = idx == -1
    c = cls[static] if cls is not None else own[0][static] if own is not None else \
        np.full(int(static.sum()), opts.static_class, np.uint8)
    cloud.add_static(points[static], c)
    counts.object_points += int((idx >= 0).sum()) if dynamic is not None else int((~static).sum())
    counts.static_points += int(static.sum())


def add_sweep(cloud: Cloud, points: np.ndarray, boxes: tuple[BoxRecord, ...], static_index: NearestIndex | None,
              object_index: dict[str, NearestIndex], opts: LabelOptions, counts: SceneCounts,
              dynamic: np.ndarray | None = None, t_us: int = 0, dynamic_index: NearestIndex | None = None,
              own: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """A sweep's points: without lidarseg (`static_index` None) as a keyframe's; with it, each point
    takes the class of the nearest labelled keyframe point, of its box's instance (box frame) or of
    the static scene (global), whichever is nearer (an in-box point with neither in reach: the box's
    class). A static point with no labelled point in reach is dropped (counted). With `dynamic`
    (carving; for sweeps always the rule for unclassified points: their classes are borrowed), a point
    outside boxes marked there is a dynamic point of frame `t_us` with the class of the nearest dynamic
    keyframe point (`dynamic_index`; none in reach: `dynamic_class`). No ground test here: the nearest
    static keyframe point of a mover's sweep point is often the road under it (its keyframe points are
    elsewhere then), which would keep the mover's low points static and smear them."""
    if static_index is None:
        add_keyframe(cloud, points, None, boxes, opts, counts, dynamic, t_us, own)
        return
    idx = in_boxes(points, boxes if opts.use_boxes else (), opts)
    cls_s, d2_s = static_index.query(points)
    for b in np.unique(idx[idx >= 0]):
        sel = np.flatnonzero(idx == b)
        box = boxes[b]
        p_box = to_box(box, points[sel])
        index = object_index.get(box.instance_token)
        if index is None:
            cls_o, d2_o = np.full(len(sel), NO_LABEL, np.uint8), np.full(len(sel), np.inf)
        else:
            cls_o, d2_o = index.query(p_box)
        own = d2_o <= d2_s[sel]
        cloud.add_object(box.instance_token, p_box[own],
                         np.where(cls_o[own] == NO_LABEL, box_class(box), cls_o[own]).astype(np.uint8))
        counts.object_points += int(own.sum())
        idx[sel[own]] = -2  # placed with its instance
        idx[sel[~own]] = -1
    if dynamic is not None:
        moving = np.flatnonzero((idx == -1) & dynamic)
        cls_d = (dynamic_index.query(points[moving])[0] if dynamic_index is not None
                 else np.full(len(moving), NO_LABEL, np.uint8))
        c = np.where(cls_d == NO_LABEL, opts.dynamic_class, cls_d).astype(np.uint8)
        cloud.add_dynamic(t_us, points[moving], c)
        counts.dynamic_points += len(moving)
        idx[moving] = -2
    static = idx == -1
    labelled = static & (cls_s != NO_LABEL)
    counts.dropped_unlabelled += int((static & ~labelled).sum())
    cloud.add_static(points[labelled], cls_s[labelled])
    counts.static_points += int(labelled.sum())
