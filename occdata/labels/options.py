"""How a scene is labelled (`LabelOptions`), what labelling reads (`LabelSources`) and what it counts
(`SceneCounts`): the records `occdata.labels.scene.label_scene` takes and returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occdata.constants import NUM_CLASSES
from occdata.labels.carve import CarveOptions
from occdata.labels.flat import FLAT_CLASS
from occdata.labels.paint import ImageMasks
from occdata.nuscenes import NuScenesDataset, SceneRecord
from occdata.nuscenes.annotations import Annotations

__all__ = ["LabelOptions", "LabelSources", "SceneCounts"]


@dataclass(frozen=True)
class LabelOptions:
    """How a scene is labelled (recorded in the manifest).

    all_sweeps: also aggregate the non-keyframe sweeps (`--all-sweeps`; a bool, unlike the store's
    `SampleOptions.lidar_sweeps`, a count). knn_radius: metres within which a sweep
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
    masks where there is no lidarseg (`occdata.labels.paint`; None: none).
    deskew: place each point of a file with per-point times by the ego pose of its own time
    (`occdata.labels.deskew`; for clouds not motion-compensated already)."""

    all_sweeps: bool = False
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
    deskew: bool = False

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
        """Whether static points on the ground take `ground_class` (without lidarseg, `occdata.labels.flat`)."""
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

    @property
    def segmented(self) -> bool:
        """Whether the tree has lidarseg (it labels the reference LiDAR's keyframes alone)."""
        return bool(self.lidarseg) and self.lidarseg_lut is not None


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

    def add_frame(self, n_points: int, n_on_ego: int) -> None:
        """Count a frame read: its points and those dropped on the ego car."""
        self.frames += 1
        self.points += n_points
        self.dropped_ego += n_on_ego
