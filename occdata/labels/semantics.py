"""Classes of a scene's points where it has no lidarseg: the ground from geometry (`occdata.labels.flat`)
and the user's own 2D masks (`occdata.labels.paint`), and how a keyframe's votes become its semantics
with them. Without either (`--ground-class` equal to `--static-class`, no `--image-masks`) nothing here
runs and labels are made as before.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.labels.boxes import in_boxes
from occdata.labels.carve import CarveGrid
from occdata.labels.flat import FLAT_CLEARANCE, SceneGround, fill_flat, fold_votes, on_ground, tiered_majority, uncover
from occdata.labels.frames import off_ego_rays, scene_frames
from occdata.labels.heights import ground_cells, height_offsets
from occdata.labels.kernels import NO_LABEL, majority
from occdata.labels.options import LabelOptions, LabelSources
from occdata.labels.paint import Painter
from occdata.nuscenes.annotations import BoxRecord

__all__ = ["SceneClasses", "scene_classes"]

_K = NUM_CLASSES - 1  # Occ3D's semantic classes (17 is free)


@dataclass(frozen=True, eq=False)
class SceneClasses:
    """A scene's point classes without lidarseg: on its `ground` (None: not split) `ground_class`,
    `static_class` elsewhere, each replaced by its painted class where the masks give one (`painter`;
    then votes carry two tiers, `occdata.labels.flat`)."""

    opts: LabelOptions
    ground: SceneGround | None
    painter: Painter | None

    @property
    def n(self) -> int:
        """The classes a vote key holds: two tiers with masks."""
        return _K * (2 if self.painter is not None else 1)

    def of(self, points: np.ndarray, t_us: int, boxes: tuple[BoxRecord, ...]) -> tuple[np.ndarray, np.ndarray]:
        """`(N,) uint8` each: the class of each of a frame's `points (N, 3)` (global, taken at `t_us`;
        `boxes`: the frame's) if it is static, and if it is dynamic."""
        o = self.opts
        static = np.full(len(points), o.static_class, np.uint8)
        if self.ground is not None:
            static[on_ground(points, t_us, self.ground, FLAT_CLEARANCE)] = o.ground_class
        dynamic = np.full(len(points), o.dynamic_class, np.uint8)
        if self.painter is None:
            return static, dynamic
        painted = self.painter.paint(points, t_us, boxes, in_boxes(points, boxes, o) if boxes else None)
        voted = painted != NO_LABEL
        return (np.where(voted, painted, static + _K).astype(np.uint8),
                np.where(voted, painted, dynamic + _K).astype(np.uint8))

    def semantics(self, votes: list[np.ndarray], shape: tuple[int, int, int]) -> tuple[np.ndarray, list[np.ndarray]]:
        """A keyframe's `(X, Y, Z) uint8` semantics from its vote keys (`n` classes): two tiers with masks
        (geometric flat voxels filled from the masks' next to them), covered flat voxels uncovered; and
        the votes as plain keys (17 classes) for densification and flow."""
        if self.painter is not None:
            semantics, by_geometry = tiered_majority(votes, shape, _K, FREE_LABEL)
            semantics = fill_flat(semantics, by_geometry, self.opts.ground_class)
            votes = fold_votes(votes, _K)
        else:
            semantics = majority(votes, shape, _K, FREE_LABEL)
        if self.ground is not None:
            semantics = uncover(semantics, votes, _K, self.opts.ground_class, FREE_LABEL)
        return semantics, votes


def scene_classes(inputs: LabelSources, indices: list[int], opts: LabelOptions, carve_grid: CarveGrid | None,
                  withheld: bool, should_stop: Callable[[], None]) -> SceneClasses | None:
    """The classes of a scene without lidarseg (`SceneClasses`; None when neither the ground nor masks
    apply). The ground's heights are carving's when the scene is carved, else fitted alike here."""
    if not opts.splits_ground and opts.image_masks is None:
        return None
    ground = _scene_ground(inputs, indices, carve_grid, should_stop) if opts.splits_ground else None
    painter = None
    if opts.image_masks is not None:
        near = None if withheld else lambda i, t: _boxes_near(inputs, i, t)
        painter = Painter(inputs.dataset, opts.image_masks, near)
    return SceneClasses(opts, ground, painter)


def _scene_ground(inputs: LabelSources, indices: list[int], carve_grid: CarveGrid | None,
                  should_stop: Callable[[], None]) -> SceneGround:
    """`SceneGround` from the keyframes, one slot per sample (its LiDARs together), heights aligned as
    carving aligns them (`occdata.labels.heights`; carving's own offsets when the scene is carved)."""
    slots = []
    for i in indices:
        should_stop()
        rays = [off_ego_rays(rec) for _, _, rec in scene_frames(inputs.dataset, [i], False)]
        slots.append((rays[0][0], np.concatenate([p for _, p in rays]), inputs.dataset.samples[i].lidar.timestamp))
    if carve_grid is not None:
        heights = carve_grid.heights
    else:
        cells = [ground_cells(p, o) for o, p, _ in slots]
        heights = height_offsets(cells, np.array([o for o, _, _ in slots]), [t for _, _, t in slots])
    return SceneGround.fit(slots, heights)


def _boxes_near(inputs: LabelSources, i: int, t_us: int) -> tuple[BoxRecord, ...]:
    """Sample `i`'s boxes at `t_us` (a camera's time near it): interpolated towards its prev or its next."""
    ds, ann = inputs.dataset, inputs.annotations
    s = ds.samples[i]
    try:
        if t_us < s.timestamp and s.prev:
            prev = ds.sample(s.prev)
            return ann.boxes_at(s.token, prev.token, prev.timestamp, s.timestamp, t_us)
        if t_us > s.timestamp and s.next:
            nxt = ds.sample(s.next)
            return ann.boxes_at(nxt.token, s.token, s.timestamp, nxt.timestamp, t_us)
    except KeyError:  # a neighbour outside the scene's slice: the sample's own boxes
        pass
    return ann.boxes_at(s.token, "", 0, 0, t_us)
