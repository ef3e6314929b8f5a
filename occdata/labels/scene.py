"""One scene's Occ3D-style labels from its LiDAR frames and 3D boxes (DESIGN §5.5).

1. Every LiDAR frame (keyframes; with `lidar_sweeps`, also the sweeps between them) is moved into
   the global frame through its own ego pose (motion compensation per frame); points on the ego car
   are dropped.
2. A point inside a box of that frame's time (the devkit's interpolated boxes) belongs to the box's
   instance and is stored in the box frame, so a moving object accumulates without smearing. The
   other points are the static scene, stored in the global frame.
3. Classes: keyframe points take their lidarseg class (32 -> Occ3D 16 + others; noise and ego
   dropped); sweep points take the class of the nearest labelled keyframe point (the same instance's
   points in the box frame, or the static points in global). Without lidarseg a box point takes its
   box's category and a static point takes `static_class`, stated in the manifest.
4. Per keyframe: the static points plus each instance's points placed at that keyframe's box pose,
   cropped to the key-ego grid, majority vote per voxel; then `mask_lidar` / `mask_camera` from
   occdata.visibility.
5. Optionally (`flow`), per voxel the ground velocity of the box whose points won its vote (the devkit's
   `box_velocity`, rotated into the grid's frame); 0 for the static scene and free space.
6. Carving (`carve`; by default exactly in the scenes without boxes): the points outside every box are
   split into static and dynamic by the scene's own rays (`occdata.labels.carve`). The static ones are
   aggregated as above; a dynamic point is drawn only at the keyframes within `carve_options.window`
   seconds of its frame, where it was then. Every LiDAR of the rig takes part: each frame's points
   through its own calibration and ego pose, each ray from its own LiDAR's origin.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Collection
from dataclasses import dataclass, field

import numpy as np

from occdata.constants import EGO_BOX, FREE_LABEL, NUM_CLASSES, OccGrid
from occdata.errors import OccDataError
from occdata.formats.gridspec import GRID_PRESETS, GridSpec, LabelFrame
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.carve import CarveGrid, CarveOptions, time_slots
from occdata.labels.densify import densify
from occdata.labels.flat import (
    FLAT_CLASS,
    FLAT_CLEARANCE,
    SceneGround,
    fill_flat,
    fold_votes,
    on_ground,
    tiered_majority,
    uncover,
)
from occdata.labels.heights import GroundMap, HeightOffsets, ground_cells, ground_map, height_offsets
from occdata.labels.kernels import NO_LABEL, NearestIndex, majority, points_in_boxes, vote_sources, vote_voxels
from occdata.labels.paint import ImageMasks, Painter
from occdata.nuscenes import LidarRecord, NuScenesDataset, SampleRecord, SceneRecord, load_lidar_points
from occdata.nuscenes.annotations import Annotations, BoxRecord, boxes_for_lidar, moving_instances
from occdata.nuscenes.lidarseg import DROP, OCC3D_FROM_LIDARSEG, read_lidarseg
from occdata.visibility import GROUND_CLASSES, camera_mask, lidar_mask

__all__ = ["LabelOptions", "LabelSources", "SceneCounts", "carve_region", "label_scene"]

# Densification casts about this many keyframes' worth of other keyframes' rays (`_static_rays`).
STATIC_RAY_FRAMES = 8
# Occ3D classes that are never an object's own points (ground, buildings, vegetation).
_STUFF = np.array(sorted({*GROUND_CLASSES, 15, 16}), np.uint8)


@dataclass(frozen=True)
class LabelOptions:
    """How a scene is labelled (recorded in the manifest).

    lidar_sweeps: also aggregate the non-keyframe sweeps. knn_radius: metres within which a sweep
    point finds a labelled keyframe point (none: the point is dropped, counted). box_margin: metres
    added to each box's sides and top when deciding membership (LiDAR returns lie on the surface).
    floor_margin: without lidarseg, points this close above a box's floor stay static (ground).
    static_class: the Occ3D class of static points when there is no lidarseg. use_boxes=False is
    the control that aggregates every point in the global frame (moving objects smear); without
    lidarseg its boxes still give their points' classes. hold_static: an instance whose box centre
    spans less than this many metres in x and y over the scene is parked (`moving_instances`): at
    keyframes where it has no box (annotation stops once an object is out of sight) it is drawn at
    its nearest annotated pose (0: never). densify: fill the insides of objects' boxes and of solid
    static surfaces, and holes in surfaces, where no ray saw free space (`occdata.labels.densify`).
    carve: split the points outside boxes into static and dynamic by free-space carving (None: in
    the scenes without boxes only; True: also on top of boxes; False: never). With carve True and
    use_boxes False the boxes are withheld altogether (`--boxes none`). dynamic_class: the Occ3D class
    of dynamic points without lidarseg; carve_options: the evidence rules (`occdata.labels.carve`).
    ground_class: without lidarseg, the Occ3D class of static points on the scene's ground
    (`occdata.labels.flat`; equal to static_class: no split). image_masks: classes from the user's 2D
    masks where there is no lidarseg (`occdata.labels.paint`; None: none)."""

    lidar_sweeps: bool = False
    knn_radius: float = 0.5
    box_margin: float = 0.1
    floor_margin: float = 0.15
    static_class: int = 0
    hold_static: float = 1.0
    use_boxes: bool = True  # False: naive global aggregation, the smearing control
    densify: bool = False
    carve: bool | None = None
    dynamic_class: int = 4
    carve_options: CarveOptions = CarveOptions()
    ground_class: int = FLAT_CLASS
    image_masks: ImageMasks | None = None

    def __post_init__(self) -> None:
        if not 0 < self.knn_radius <= 5:
            raise ValueError("knn_radius must be in (0, 5] m")
        if not 0 <= self.hold_static <= 10:
            raise ValueError("hold_static must be in [0, 10] m")
        if not 0 <= self.box_margin <= 1 or not 0 <= self.floor_margin <= 1:
            raise ValueError("box_margin and floor_margin must be in [0, 1] m")
        if not 0 <= self.static_class < NUM_CLASSES - 1:
            raise ValueError(f"static_class must be an Occ3D class 0..{NUM_CLASSES - 2}")
        if not 0 <= self.dynamic_class < NUM_CLASSES - 1:
            raise ValueError(f"dynamic_class must be an Occ3D class 0..{NUM_CLASSES - 2}")
        if not 0 <= self.ground_class < NUM_CLASSES - 1:
            raise ValueError(f"ground_class must be an Occ3D class 0..{NUM_CLASSES - 2}")

    @property
    def splits_ground(self) -> bool:
        """Whether static points on the ground take `ground_class` (without lidarseg; `occdata.labels.flat`)."""
        return self.ground_class != self.static_class

    def carves(self, has_boxes: bool, keyframes: int = 2) -> bool:
        """Whether a scene with (`has_boxes`) or without boxes, of `keyframes` keyframes, is carved. By
        default (`carve` None) the scenes without boxes are, unless they have one keyframe: carving needs
        other times' rays, and one keyframe's own points do not smear (such a scene is labelled naively)."""
        return (not has_boxes and keyframes > 1) if self.carve is None else self.carve

    def mode(self, has_boxes: bool, keyframes: int = 2) -> str:
        """How a scene is labelled, in a word: boxes, naive (every point static), carve, boxes+carve."""
        boxes = has_boxes and self.use_boxes
        if self.carves(has_boxes, keyframes):
            return "boxes+carve" if boxes else "carve"
        return "boxes" if boxes else "naive"


@dataclass(frozen=True, eq=False)
class LabelSources:
    """What labelling reads besides the LiDAR files: the tables (`dataset`, read with sweeps when
    sweeps are used), the boxes and the lidarseg files (`lidarseg`: sample_data token -> path; empty
    when the tree has none)."""

    dataset: NuScenesDataset
    annotations: Annotations
    lidarseg: dict[str, object] = field(default_factory=dict)
    lidarseg_lut: np.ndarray | None = None  # (256,) uint8: lidarseg index -> Occ3D class or DROP

    def for_scene(self, scene: SceneRecord) -> LabelSources:
        """What labelling `scene` reads and nothing else: its samples (with their sweeps), their
        boxes and lidarseg files. A task carries this slice, so a worker's memory does not grow with
        the tree (a sweep's boxes need only its own sample and that sample's `prev`, both in the scene)."""
        ds = self.dataset.scene_slice(scene)
        lidar_tokens = [rec.token for s in ds.samples for rec in (s.lidar, *s.sweeps)]  # lidarseg: LIDAR_TOP only
        return LabelSources(ds, self.annotations.for_samples(scene.sample_tokens),
                           {t: self.lidarseg[t] for t in lidar_tokens if t in self.lidarseg}, self.lidarseg_lut)


@dataclass
class SceneCounts:
    """Per-scene point counts (the manifest's figures)."""

    keyframes: int = 0
    frames: int = 0
    points: int = 0
    static_points: int = 0
    object_points: int = 0
    dropped_ego: int = 0
    dropped_class: int = 0  # lidarseg noise / ego
    dropped_unlabelled: int = 0  # sweep points with no labelled keyframe point within knn_radius
    instances: int = 0
    # Carving only (left out of a scene's record otherwise): the labelling mode, points found dynamic,
    # and the carve grid's voxels.
    mode: str = "boxes"
    dynamic_points: int = 0
    carve_voxels: int = 0


@dataclass(frozen=True, eq=False)
class _SceneClasses:
    """Where a scene has no lidarseg, its points' classes from geometry and masks: on the scene's
    `ground` (`heights` aligned; None: not split) `ground_class`, `static_class` elsewhere, each
    replaced by its painted class where the user's masks give one (`painter`; then two tiers of votes,
    `occdata.labels.flat`). `boxes_at(i, t)`: sample i's boxes at time t, for the painter."""

    opts: LabelOptions
    ground: SceneGround | None
    painter: Painter | None

    @property
    def n(self) -> int:
        """The classes a vote key holds: two tiers with masks."""
        return (NUM_CLASSES - 1) * (2 if self.painter is not None else 1)

    def of(self, points: np.ndarray, t_us: int, boxes: tuple[BoxRecord, ...]) -> tuple[np.ndarray, np.ndarray]:
        """`(N,) uint8` each: the class of each of a frame's `points (N, 3)` (global, at `t_us`; `boxes`:
        the frame's) if it is static, and if it is dynamic."""
        o = self.opts
        static = np.full(len(points), o.static_class, np.uint8)
        if self.ground is not None:
            static[on_ground(points, t_us, self.ground, FLAT_CLEARANCE)] = o.ground_class
        dynamic = np.full(len(points), o.dynamic_class, np.uint8)
        if self.painter is None:
            return static, dynamic
        painted = self.painter.paint(points, t_us, boxes, _in_boxes(points, boxes, o) if boxes else None)
        voted = painted != NO_LABEL
        k = NUM_CLASSES - 1
        return (np.where(voted, painted, static + k).astype(np.uint8),
                np.where(voted, painted, dynamic + k).astype(np.uint8))

    def semantics(self, votes: list[np.ndarray], shape: tuple[int, int, int]) -> tuple[np.ndarray, list[np.ndarray]]:
        """A keyframe's `(X, Y, Z) uint8` semantics from its vote keys (`_votes` with `n` classes), covered
        flat voxels uncovered; and the votes as plain keys (17 classes) for densification and flow."""
        k = NUM_CLASSES - 1
        if self.painter is not None:
            semantics, by_geometry = tiered_majority(votes, shape, k, FREE_LABEL)
            semantics = fill_flat(semantics, by_geometry, self.opts.ground_class)
            votes = fold_votes(votes, k)
        else:
            semantics = majority(votes, shape, k, FREE_LABEL)
        if self.ground is not None:
            semantics = uncover(semantics, votes, k, self.opts.ground_class, FREE_LABEL)
        return semantics, votes


@dataclass
class _Cloud:
    """Points gathered over a scene: static ones in global, object ones per instance in its box frame."""

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


def _frame_points(rec: LidarRecord) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A frame's points `(N, 3) float64` in global, the lidar origin in global `(3,)`, and
    `(N,) bool` off the ego car."""
    raw = load_lidar_points(rec.path)[:, :3].astype(np.float64)
    points_ego = transform_points(rec.T_ego_from_lidar, raw)
    lo, hi = np.array(EGO_BOX[0]), np.array(EGO_BOX[1])
    off_ego = ~((points_ego >= lo) & (points_ego <= hi)).all(axis=1)
    T_global_from_lidar = rec.T_global_from_ego @ rec.T_ego_from_lidar
    return transform_points(rec.T_global_from_ego, points_ego), T_global_from_lidar[:3, 3].copy(), off_ego


def _to_box(box: BoxRecord, points: np.ndarray) -> np.ndarray:
    """Global points `(N, 3)` in `box`'s frame, `(N, 3) float64`."""
    return transform_points(invert_rigid(box.T_global_from_box()), points)


def _in_boxes(points: np.ndarray, boxes: tuple[BoxRecord, ...], opts: LabelOptions) -> np.ndarray:
    """`(N,) int32` index of the (margin-grown) box holding each global point `(N, 3)`, or -1."""
    if not boxes:
        return np.full(len(points), -1, np.int32)
    T, half = _box_frames(boxes, opts.box_margin)
    return points_in_boxes(np.ascontiguousarray(points), T, half)


def _members(points: np.ndarray, cls: np.ndarray | None, boxes: tuple[BoxRecord, ...],
             opts: LabelOptions) -> np.ndarray:
    """`(N,) int32` box index of each global point `(N, 3)`, or -1 for static. With classes, ground,
    building and vegetation points in a box stay static; without, points near a box's floor do."""
    idx = _in_boxes(points, boxes, opts)
    if cls is not None:
        idx[np.isin(cls, _STUFF)] = -1
        return idx
    for b in np.unique(idx[idx >= 0]):
        sel = np.flatnonzero(idx == b)
        z_box = _to_box(boxes[b], points[sel])[:, 2]
        idx[sel[z_box < -boxes[b].size_wlh[2] / 2 + opts.floor_margin]] = -1
    return idx


def _add_keyframe(cloud: _Cloud, points: np.ndarray, cls: np.ndarray | None, boxes: tuple[BoxRecord, ...],
                  opts: LabelOptions, counts: SceneCounts, dynamic: np.ndarray | None = None, t_us: int = 0,
                  own: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Split a keyframe's global points into static and per-instance (box frame) points with classes;
    with `dynamic (N,) bool` (carving) the points outside boxes marked there, less ground, buildings and
    vegetation by lidarseg, are kept as frame `t_us`'s dynamic points instead of static ones. `own`
    (without lidarseg): each point's class if static and if dynamic, `(N,) uint8` each (`_SceneClasses`;
    None: `static_class` and `dynamic_class`)."""
    idx = _members(points, cls, boxes, opts)
    for b in np.unique(idx[idx >= 0]):
        sel = idx == b
        box = boxes[b]
        c = cls[sel] if cls is not None else np.full(int(sel.sum()), box_class(box), np.uint8)
        if opts.use_boxes:
            p_box = _to_box(box, points[sel])
            cloud.add_object(box.instance_token, p_box, c)
        else:  # the control: the box gives the class only, the point stays where it was seen
            cloud.add_static(points[sel], c)
    static = idx < 0
    if dynamic is not None:
        moving = static & dynamic & (True if cls is None else ~np.isin(cls, _STUFF))
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


def _add_sweep(cloud: _Cloud, points: np.ndarray, boxes: tuple[BoxRecord, ...], static_index: NearestIndex | None,
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
        _add_keyframe(cloud, points, None, boxes, opts, counts, dynamic, t_us, own)
        return
    idx = _in_boxes(points, boxes if opts.use_boxes else (), opts)
    cls_s, d2_s = static_index.query(points)
    for b in np.unique(idx[idx >= 0]):
        sel = np.flatnonzero(idx == b)
        box = boxes[b]
        p_box = _to_box(box, points[sel])
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


def _keyframe_classes(inputs: LabelSources, rec: LidarRecord, n_points: int) -> np.ndarray | None:
    """`(N,) uint8` Occ3D classes (DROP for noise / ego) of a keyframe's points from lidarseg, or None."""
    path = inputs.lidarseg.get(rec.token)
    if path is None or inputs.lidarseg_lut is None:
        return None
    return inputs.lidarseg_lut[read_lidarseg(path, n_points)]


def T_grid_from_keyego(sample: SampleRecord, spec: GridSpec) -> np.ndarray:
    """`(4, 4) float64`: the keyframe's key ego -> the grid's frame (itself, or the LIDAR_TOP sensor)."""
    if spec.frame is LabelFrame.LIDAR:
        return invert_rigid(sample.lidar.T_ego_from_lidar)  # the keyframe sweep's ego is the key ego
    return np.eye(4)


def _votes(static: tuple[np.ndarray, np.ndarray], cloud: _Cloud, boxes: tuple[BoxRecord, ...],
           T_grid_from_global: np.ndarray, grid: OccGrid, dynamic: tuple[np.ndarray, np.ndarray] | None = None,
           n: int = NUM_CLASSES - 1) -> tuple[list[np.ndarray], list[int]]:
    """`vote_voxels` keys on `grid` of the static points (first; with them the keyframe's `dynamic`
    points, global, where they were then: they have no box, so no flow) and of each box's instance
    points placed at that box's pose (then one list per box with points), and the index in `boxes` of
    each list after the first. `n`: the classes a key holds (34 with two tiers, `occdata.labels.flat`)."""
    shape = np.array(grid.shape, np.int64)
    lower = np.array(grid.lower, np.float64)
    votes = [vote_voxels(static[0], static[1], T_grid_from_global, lower, grid.voxel_size, shape, n)]
    if dynamic is not None and len(dynamic[0]):
        votes[0] = np.concatenate([votes[0], vote_voxels(np.ascontiguousarray(dynamic[0]), dynamic[1],
                                                         T_grid_from_global, lower, grid.voxel_size, shape, n)])
    box_of_vote = []
    for b, box in enumerate(boxes):  # (none placed in the control: it has no instance points)
        pts, cls = cloud.instance(box.instance_token)
        if len(pts):
            T = T_grid_from_global @ box.T_global_from_box()
            votes.append(vote_voxels(np.ascontiguousarray(pts), cls, T, lower, grid.voxel_size, shape, n))
            box_of_vote.append(b)
    return votes, box_of_vote


def _flow(votes: list[np.ndarray], box_of_vote: list[int], semantics: np.ndarray, v_global: np.ndarray,
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


Rays = list[tuple[np.ndarray, np.ndarray]]  # a keyframe's rays per LiDAR: (origin (3,), points (N, 3)), global


def _rays_in(T: np.ndarray, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
    """Every LiDAR's rays of a keyframe moved by `T (4, 4)`: origins and endpoints `(N, 3) float64`
    (one LiDAR: its origin broadcast, as before several LiDARs were read)."""
    ends = [transform_points(T, pts) for _, pts in rays]
    origins = [np.broadcast_to(transform_points(T, o[None])[0], e.shape) for (o, _), e in zip(rays, ends, strict=True)]
    if len(rays) == 1:
        return origins[0], ends[0]
    return np.concatenate(origins), np.concatenate(ends)


def _masks(semantics: np.ndarray, sample: SampleRecord, rays: Rays, spec: GridSpec) -> tuple[np.ndarray, ...]:
    """`mask_lidar`, `mask_camera` `(X, Y, Z) uint8` of a keyframe on `spec`'s grid: the keyframe's rays of
    every LiDAR (`Rays`, each from its own origin) traversed, plus every occupied voxel (their points
    were observed, by some frame); the camera mask within it (occdata.visibility)."""
    lower = np.array(spec.grid.lower, np.float64)
    T_grid_from_key = T_grid_from_keyego(sample, spec)
    T_grid_from_global = T_grid_from_key @ invert_rigid(sample.T_global_from_keyego)
    origins, ends = _rays_in(T_grid_from_global, rays)
    m_lidar = lidar_mask(semantics, origins, ends, lower, spec.grid.voxel_size) | (semantics != FREE_LABEL)
    m_lidar = m_lidar.astype(np.uint8)
    rig = sample.camera_rig()
    T_cam_from_grid = rig.T_cam_from_keyego @ invert_rigid(T_grid_from_key)
    return m_lidar, camera_mask(semantics, m_lidar, rig.K, T_cam_from_grid, rig.image_size, lower,
                                spec.grid.voxel_size)


def _densify(semantics: np.ndarray, votes: list[np.ndarray], box_of_vote: list[int], boxes: tuple[BoxRecord, ...],
             rays: Rays, T_grid_from_global: np.ndarray, grid: OccGrid,
             static_rays: tuple[np.ndarray, np.ndarray], solids: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """`densify` of one keyframe's `semantics` with its rays (global) and the boxes whose instance votes
    in this grid (an object is filled only where its points are seen), and `static_rays` (global; other
    keyframes' rays, `_static_rays`) as evidence for the static scene; `solids`: the static classes are
    lidarseg's (else no walk behind surfaces, `densify`): the new semantics, and `(X, Y, Z) int64` the index
    in `boxes` of the box that filled each voxel (-1: none)."""
    seen = [box_of_vote[m] for m in range(len(box_of_vote)) if len(votes[m + 1])]
    T = np.array([invert_rigid(T_grid_from_global @ boxes[b].T_global_from_box()) for b in seen]).reshape(-1, 4, 4)
    half = np.array([[boxes[b].size_wlh[1] / 2, boxes[b].size_wlh[0] / 2, boxes[b].size_wlh[2] / 2] for b in seen])
    cls = np.array([box_class(boxes[b]) for b in seen], np.uint8)
    more = tuple(transform_points(T_grid_from_global, a) for a in static_rays)
    if len(rays) == 1:  # as before several LiDARs were read (byte-identical)
        origin = transform_points(T_grid_from_global, rays[0][0][None])[0]
        ends = transform_points(T_grid_from_global, rays[0][1])
    else:  # each ray from its own LiDAR; the walks behind surfaces start from the reference LiDAR
        origin, ends = _rays_in(T_grid_from_global, rays)
    dense, owner = densify(semantics, origin, ends, T, half.reshape(-1, 3),
                           cls, np.array(grid.lower, np.float64), grid.voxel_size, more, solids)
    return dense, np.where(owner >= 0, np.append(np.asarray(seen, np.int64), -1)[owner], -1)


def _grid_labels(static: tuple[np.ndarray, np.ndarray], cloud: _Cloud, boxes: tuple[BoxRecord, ...],
                 sample: SampleRecord, rays: Rays, spec: GridSpec,
                 masks: bool, v_global: np.ndarray | None = None,
                 static_rays: tuple[np.ndarray, np.ndarray] | None = None,
                 dynamic: tuple[np.ndarray, np.ndarray] | None = None, solids: bool = True,
                 classes: _SceneClasses | None = None) -> dict[str, np.ndarray]:
    """One keyframe on one grid: `semantics` in Occ3D classes (17 = free) and, with `masks`, the masks;
    all `(X, Y, Z) uint8` in the grid's frame. With `v_global (B, 3)` (m/s, global, one row per box of
    `boxes`, NaN as 0) also `flow (X, Y, Z, 2) float32` (`_flow`). With `static_rays` (`_static_rays`),
    `_densify` the semantics before the masks (a voxel a box filled takes its flow). `dynamic`: the
    keyframe's dynamic points and classes (carving; global). `classes`: the scene's ground and masks
    (`_SceneClasses`; None: a plain majority)."""
    T = T_grid_from_keyego(sample, spec) @ invert_rigid(sample.T_global_from_keyego)
    if classes is None:
        votes, box_of_vote = _votes(static, cloud, boxes, T, spec.grid, dynamic)
        semantics = majority(votes, spec.grid.shape, NUM_CLASSES - 1, FREE_LABEL)
    else:
        votes, box_of_vote = _votes(static, cloud, boxes, T, spec.grid, dynamic, classes.n)
        semantics, votes = classes.semantics(votes, spec.grid.shape)
    filled_by = None
    if static_rays is not None:
        semantics, filled_by = _densify(semantics, votes, box_of_vote, boxes, rays, T, spec.grid, static_rays,
                                        solids)
    out = {"semantics": semantics}
    if masks:
        out["mask_lidar"], out["mask_camera"] = _masks(semantics, sample, rays, spec)
    if v_global is not None:
        out["flow"] = _flow(votes, box_of_vote, semantics, v_global, T[:3, :3], filled_by)
    return out


def _box_velocities(inputs: LabelSources, keyframe_boxes: list[tuple[BoxRecord, ...]],
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


def _static_rays(rays: list[Rays], n: int, budget: int = STATIC_RAY_FRAMES) -> tuple[np.ndarray, np.ndarray]:
    """Densification's evidence for the static scene at keyframe `n`: the rays (`Rays`: per LiDAR, origin
    `(3,)`, points `(N, 3)`, global) of the scene's other keyframes, each thinned to every `s`-th ray
    (offset by `n`) so that about `budget` keyframes' worth are cast: more viewpoints, bounded cost.
    Returns origins and endpoints `(M, 3) float64`."""
    stride = max(1, -(-len(rays) // budget))
    picked = [(o, pts[(m + n) % stride::stride]) for m, frame in enumerate(rays) if m != n for o, pts in frame]
    if not picked:
        return np.zeros((0, 3)), np.zeros((0, 3))
    origins = np.concatenate([np.broadcast_to(o, p.shape) for o, p in picked])
    return origins, np.concatenate([p for _, p in picked])


def _held_static(keyframe_boxes: list[tuple[BoxRecord, ...]], travel: float) -> list[tuple[BoxRecord, ...]]:
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


def _no_stop() -> None:
    pass


def _frame_boxes(inputs: LabelSources, sample_index: int, k: int, rec: LidarRecord) -> tuple[BoxRecord, ...]:
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


def carve_region(samples: list[SampleRecord], grids: tuple[GridSpec, ...],
                 pad: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The global axis-aligned box `(lo (3,), hi (3,))` (m) holding every keyframe's `grids` (their
    corners through each keyframe's key-ego pose), grown by `pad`: where carving can change a label."""
    corners = []
    for s in samples:
        for spec in grids:
            lo, hi = np.array(spec.grid.lower, np.float64), np.array(spec.grid.upper, np.float64)
            box = np.array([[(lo, hi)[a][0], (lo, hi)[b][1], (lo, hi)[c][2]] for a in (0, 1) for b in (0, 1)
                            for c in (0, 1)])
            T_global_from_grid = s.T_global_from_keyego @ invert_rigid(T_grid_from_keyego(s, spec))
            corners.append(transform_points(T_global_from_grid, box))
    every = np.concatenate(corners)
    return every.min(axis=0) - pad, every.max(axis=0) + pad


def _frames(ds: NuScenesDataset, indices: list[int], sweeps: bool) -> list[tuple[int, int, LidarRecord]]:
    """Every LiDAR frame of the scene as (sample index, LiDAR index in rig order, record): keyframes,
    then (with `sweeps`) each keyframe's sweeps of each LiDAR."""
    out = [(i, k, rec) for i in indices for k, rec in enumerate(ds.samples[i].lidars)]
    if sweeps:
        out += [(i, k, rec) for i in indices for k in range(len(ds.samples[i].lidars))
                for rec in ds.samples[i].sweeps_of(k)]
    return out


def _carve(frames: list[tuple[int, int, LidarRecord]], keyframe_frames: int, lo: np.ndarray, hi: np.ndarray,
           opts: CarveOptions, should_stop: Callable[[], None]) -> CarveGrid:
    """The scene's free-space evidence (`occdata.labels.carve`): every frame's rays, from its own LiDAR,
    counted once per time slot (a keyframe's LiDARs fire together); `frames` as `_frames` gives them,
    the first `keyframe_frames` the keyframes' (the sweeps' rays are thinned, `CarveOptions.ray_stride`).
    The keyframes' ground comes first: the slots' height errors (`opts.align_heights`) and the ground map;
    the keyframes' points are then read once for both (a scene's keyframes: tens of MB)."""
    slots = time_slots([rec.timestamp for _, _, rec in frames])
    key_rays: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    heights = ground = None
    if opts.align_heights or opts.ground_clearance > 0:
        key_rays = {f: _off_ego_rays(frames[f][2]) for f in range(keyframe_frames)}
        heights, ground = _slot_ground(key_rays, frames, slots, opts.align_heights, should_stop)
    grid = CarveGrid(lo, hi, opts, heights, ground)
    for slot in np.unique(slots):
        should_stop()
        members = np.flatnonzero(slots == slot)
        rays = [key_rays.pop(f) if f in key_rays else _off_ego_rays(frames[f][2]) for f in members]
        grid.add_slot(int(slot), rays, thin=bool(members.max() >= keyframe_frames),
                      t_us=frames[members[0]][2].timestamp)
    return grid


def _off_ego_rays(rec: LidarRecord) -> tuple[np.ndarray, np.ndarray]:
    """A frame's LiDAR origin `(3,)` and its points off the ego car `(N, 3)`, float64 in global."""
    points, origin, off_ego = _frame_points(rec)
    return origin, points[off_ego]


def _slot_ground(key_rays: dict[int, tuple[np.ndarray, np.ndarray]], frames: list[tuple[int, int, LidarRecord]],
                 slots: np.ndarray, align: bool,
                 should_stop: Callable[[], None]) -> tuple[HeightOffsets | None, GroundMap]:
    """The keyframe slots' height errors (`align`; else None) and the scene's ground map
    (`occdata.labels.heights`) from the ground columns of their frames `key_rays` (frame index ->
    `_off_ego_rays`), each slot at its first frame's time and the origin of its first LiDAR. Slots are
    numbered in time order (`time_slots`), so their times increase."""
    cells, origins, times = [], [], []
    for slot in np.unique(slots[list(key_rays)]):
        should_stop()
        members = [f for f in np.flatnonzero(slots == slot) if f in key_rays]
        origin = key_rays[members[0]][0]
        cells.append(ground_cells(np.concatenate([key_rays[f][1] for f in members]), origin))
        origins.append(origin)
        times.append(frames[members[0]][2].timestamp)
    heights = height_offsets(cells, np.asarray(origins), times) if align else None
    return heights, ground_map(cells, np.zeros(len(cells)) if heights is None else heights.dz)


def _scene_classes(inputs: LabelSources, indices: list[int], opts: LabelOptions, carve_grid: CarveGrid | None,
                   withheld: bool, should_stop: Callable[[], None]) -> _SceneClasses | None:
    """The classes of a scene without lidarseg from its ground and the user's masks (`_SceneClasses`;
    None when neither applies). The ground is carving's when the scene is carved, else fitted here from
    the keyframes alike (`_slot_ground`: heights aligned)."""
    if not opts.splits_ground and opts.image_masks is None:
        return None
    ground = _scene_ground(inputs, indices, carve_grid, should_stop) if opts.splits_ground else None
    painter = None
    if opts.image_masks is not None:
        painter = Painter(inputs.dataset, opts.image_masks,
                          None if withheld else lambda i, t: _boxes_near(inputs, i, t))
    return _SceneClasses(opts, ground, painter)


def _scene_ground(inputs: LabelSources, indices: list[int], carve_grid: CarveGrid | None,
                  should_stop: Callable[[], None]) -> SceneGround:
    """The scene's ground for labels (`SceneGround`) from its keyframe slots, heights aligned as carving
    aligns them (carving's own offsets when the scene is carved)."""
    frames = _frames(inputs.dataset, indices, False)
    key_rays = {f: _off_ego_rays(rec) for f, (_, _, rec) in enumerate(frames)}
    slots = time_slots([rec.timestamp for _, _, rec in frames])
    heights = carve_grid.heights if carve_grid is not None else \
        _slot_ground(key_rays, frames, slots, True, should_stop)[0] or HeightOffsets.zero()
    per_slot = []
    for slot in np.unique(slots):
        members = np.flatnonzero(slots == slot)
        per_slot.append((key_rays[members[0]][0], np.concatenate([key_rays[f][1] for f in members]),
                         frames[members[0]][2].timestamp))
    return SceneGround.fit(per_slot, heights)


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


def label_scene(inputs: LabelSources, scene: SceneRecord, opts: LabelOptions,
                should_stop: Callable[[], None] = _no_stop, grids: tuple[GridSpec, ...] = (GRID_PRESETS["occ3d"],),
                flow: bool | Collection[str] = False,
                ) -> tuple[dict[str, dict[str, dict[str, np.ndarray]]], SceneCounts]:
    """Labels of every keyframe of `scene` on each of `grids` from one aggregation: grid name -> sample
    token -> {"semantics"[, "mask_lidar", "mask_camera"]} `(X, Y, Z) uint8` in Occ3D classes (17 = free;
    the writers map them to the grid's ids), and the scene's point counts. `flow`: True for every grid,
    or the names of the grids whose labels also hold `flow (X, Y, Z, 2) float32`, the box velocity (m/s,
    grid frame) of their object voxels (`_flow`; X*Y*Z*8 bytes a keyframe: 84 MB at 512x512x40).
    Every LiDAR of the rig is aggregated (each frame through its own calibration and ego pose); with
    carving (`LabelOptions.carves`) the points outside boxes are split by the scene's rays.
    `should_stop()` is called between frames (nothing is written here): it raises to stop the run."""
    ds = inputs.dataset
    indices = [ds.index_of(t) for t in scene.sample_tokens]
    counts = SceneCounts(keyframes=len(indices))
    has_boxes = any(inputs.annotations.boxes_by_sample.get(t) for t in scene.sample_tokens)
    carving = opts.carves(has_boxes, len(indices))
    counts.mode = opts.mode(has_boxes, len(indices))
    withheld = carving and not opts.use_boxes  # --boxes none: the boxes give nothing, not even classes
    carve_grid = None
    if carving:
        if len(indices) < 2:
            raise OccDataError(f"scene {scene.name} has {len(indices)} keyframe: too short to carve (carving needs "
                               "other times' rays); label it without --carve / --boxes none")
        frames = _frames(ds, indices, opts.lidar_sweeps)
        n_key = sum(len(ds.samples[i].lidars) for i in indices)
        carve_grid = _carve(frames, n_key, *carve_region([ds.samples[i] for i in indices], grids),
                            opts.carve_options, should_stop)
        counts.carve_voxels = int(np.prod(carve_grid.shape))

    def boxes_of(i: int, k: int, rec: LidarRecord) -> tuple[BoxRecord, ...]:
        return () if withheld else _frame_boxes(inputs, i, k, rec)

    def moving(points: np.ndarray, classified: bool, t_us: int) -> np.ndarray | None:
        return None if carve_grid is None else carve_grid.dynamic(points, t_us, classified)

    cloud = _Cloud()
    rays: dict[str, Rays] = {}
    with_seg = False
    # lidarseg labels the reference LiDAR alone: with it, the other LiDARs' keyframes are labelled as sweeps.
    seg_tree = bool(inputs.lidarseg) and inputs.lidarseg_lut is not None
    classes = None if seg_tree else _scene_classes(inputs, indices, opts, carve_grid, withheld, should_stop)

    def own(points: np.ndarray, rec: LidarRecord, boxes: tuple[BoxRecord, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        return None if classes is None else classes.of(points, rec.timestamp, boxes)
    later: list[tuple[int, int, LidarRecord]] = []
    for i in indices:  # pass 1: keyframes, the labelled references
        should_stop()  # Ctrl-C / SIGTERM of an in-process run: stop between frames
        s = ds.samples[i]
        rays[s.token] = []
        for k, rec in enumerate(s.lidars):
            points, origin, off_ego = _frame_points(rec)
            rays[s.token].append((origin, points[off_ego]))
            if k > 0 and seg_tree:
                later.append((i, k, rec))
                continue
            cls = _keyframe_classes(inputs, rec, len(points)) if k == 0 else None
            keep = off_ego if cls is None else off_ego & (cls != DROP)
            with_seg |= cls is not None
            counts.frames += 1
            counts.points += len(points)
            counts.dropped_ego += int((~off_ego).sum())
            counts.dropped_class += int((off_ego & ~keep).sum())
            boxes = boxes_of(i, k, rec)
            _add_keyframe(cloud, points[keep], None if cls is None else cls[keep], boxes, opts, counts,
                          moving(points[keep], cls is not None, rec.timestamp), rec.timestamp,
                          None if cls is not None else own(points[keep], rec, boxes))
    sweeps = later + [f for f in _frames(ds, indices, True) if f[2] not in ds.samples[f[0]].lidars] \
        if opts.lidar_sweeps else later
    if sweeps:  # pass 2: sweeps, labelled from the keyframes
        static_index = object_index = dynamic_index = None
        if with_seg:
            static_index = NearestIndex.build(*cloud.static(), opts.knn_radius)
            object_index = {k: NearestIndex.build(*cloud.instance(k), opts.knn_radius) for k in cloud.obj_pts}
            if carve_grid is not None:
                dynamic_index = NearestIndex.build(*_cat([p for _, p, _ in cloud.dyn], [c for _, _, c in cloud.dyn]),
                                                   opts.knn_radius)
        for i, k, rec in sweeps:
            should_stop()
            points, _, off_ego = _frame_points(rec)
            counts.frames += 1
            counts.points += len(points)
            counts.dropped_ego += int((~off_ego).sum())
            boxes = boxes_of(i, k, rec)
            _add_sweep(cloud, points[off_ego], boxes, static_index, object_index or {}, opts, counts,
                       moving(points[off_ego], False, rec.timestamp), rec.timestamp, dynamic_index,
                       None if with_seg else own(points[off_ego], rec, boxes))
    counts.instances = len(cloud.obj_pts)
    static = cloud.static()
    static = (np.ascontiguousarray(static[0]), np.ascontiguousarray(static[1]))
    out: dict[str, dict[str, dict[str, np.ndarray]]] = {spec.name: {} for spec in grids}
    keyframe_boxes = [boxes_of(i, 0, ds.samples[i].lidar) for i in indices]
    held = _held_static(keyframe_boxes, opts.hold_static)
    flow_names = {spec.name for spec in grids} if flow is True else set(flow or ())
    v_global = _box_velocities(inputs, keyframe_boxes, held) if flow_names else []
    # Grids that differ only in classes and layout (occ3d and openocc-v2) share one voxelisation:
    # the stored ids are mapped when written. Computed once per keyframe, with what any of them needs.
    groups: dict[tuple[object, ...], list[GridSpec]] = {}
    for spec in grids:
        groups.setdefault((spec.grid, spec.frame), []).append(spec)
    ray_list = [rays[ds.samples[i].token] for i in indices]
    for n, i in enumerate(indices):
        s = ds.samples[i]
        boxes = keyframe_boxes[n] + held[n]
        more = _static_rays(ray_list, n) if opts.densify else None
        dynamic = cloud.dynamic_at(s.timestamp, opts.carve_options.window) if carve_grid is not None else None
        for members in groups.values():
            should_stop()
            any_flow = any(g.name in flow_names for g in members)
            shared = _grid_labels(static, cloud, boxes, s, rays[s.token], members[0],
                                  any(g.masks for g in members), v_global[n] if any_flow else None,
                                  static_rays=more, dynamic=dynamic, solids=seg_tree,
                                  classes=None if with_seg else classes)
            for spec in members:
                keep = {"semantics", *(("mask_lidar", "mask_camera") if spec.masks else ()),
                        *(("flow",) if spec.name in flow_names else ())}
                out[spec.name][s.token] = {k: v for k, v in shared.items() if k in keep}
    return out, counts
