"""One scene's Occ3D-style labels from its LiDAR frames and 3D boxes (docs/design.md#labels-from-lidar).

1. Carving (`carve`; by default exactly in the scenes without boxes), first: the scene's free-space
   evidence from every frame's rays (`occdata.labels.carving`), which later splits the points outside
   every box into static and dynamic.
2. Every LiDAR frame (keyframes; with `all_sweeps`, also the sweeps between them) is moved into the
   global frame through its own ego pose (`occdata.labels.frames`); points on the ego car are dropped.
   Every LiDAR of the rig takes part, each through its own calibration and ego pose.
3. A point inside a box of that frame's time (`occdata.labels.boxes`) belongs to the box's instance
   and is stored in the box frame, so a moving object accumulates without smearing; the other points
   are the static scene (global), or dynamic (carving; drawn only at the keyframes within
   `carve_options.window` seconds of its frame, where it was then). Keyframes first, as the labelled
   references; the sweeps then borrow their classes (`occdata.labels.cloud`). Without lidarseg a point's
   class comes from the scene's ground and the user's 2D masks (`occdata.labels.semantics`).
4. Per keyframe and grid (`occdata.labels.keyframe`): the static points plus each instance's points
   placed at that keyframe's box pose, majority vote per voxel; optionally densified; the masks; and
   optionally (`flow`) the ground velocity of the box whose points won a voxel (`occdata.labels.flow`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass

import numpy as np

from occdata.errors import OccDataError
from occdata.formats.gridspec import GRID_PRESETS, GridSpec
from occdata.labels.boxes import frame_boxes, held_static
from occdata.labels.carve import CarveGrid
from occdata.labels.carving import carve_region, carve_scene
from occdata.labels.cloud import Cloud, add_keyframe, add_sweep, keyframe_classes
from occdata.labels.deskew import PoseTrack
from occdata.labels.flow import box_velocities
from occdata.labels.frames import Frame, Rays, frame_points, scene_frames, scene_track
from occdata.labels.kernels import NearestIndex
from occdata.labels.keyframe import grid_labels, static_rays
from occdata.labels.options import LabelOptions, LabelSources, SceneCounts
from occdata.labels.semantics import SceneClasses, scene_classes
from occdata.nuscenes import LidarRecord, SceneRecord
from occdata.nuscenes.annotations import BoxRecord
from occdata.nuscenes.lidarseg import DROP

__all__ = ["label_scene"]

Labels = dict[str, dict[str, dict[str, np.ndarray]]]  # grid name -> sample token -> array name -> array


def _no_stop() -> None:
    pass


@dataclass
class _Scene:
    """A scene being labelled: its samples (`indices` into the dataset), what its boxes are used for
    (`withheld`: none at all, `--boxes none`), its carve grid (None: not carved), its counts, and its
    ego poses when points are placed by their own times (`LabelOptions.deskew`; else None)."""

    inputs: LabelSources
    opts: LabelOptions
    indices: list[int]
    counts: SceneCounts
    withheld: bool
    carve_grid: CarveGrid | None
    should_stop: Callable[[], None]
    track: PoseTrack | None = None
    classes: SceneClasses | None = None  # without lidarseg: the ground's and the masks' classes

    def own(self, points: np.ndarray, t_us: int, boxes: tuple[BoxRecord, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        """Each point's class if static and if dynamic (`SceneClasses.of`), None without `classes`."""
        return None if self.classes is None else self.classes.of(points, t_us, boxes)

    def boxes(self, i: int, k: int, rec: LidarRecord) -> tuple[BoxRecord, ...]:
        """The boxes at frame `rec`'s time (`frame_boxes`), none when they are withheld."""
        return () if self.withheld else frame_boxes(self.inputs, i, k, rec)

    def moving(self, points: np.ndarray, classified: bool, t_us: int) -> np.ndarray | None:
        """`(N,) bool` carving's verdict on global points `(N, 3)` of time `t_us`; None without carving."""
        return None if self.carve_grid is None else self.carve_grid.dynamic(points, t_us, classified)


def label_scene(inputs: LabelSources, scene: SceneRecord, opts: LabelOptions,
                should_stop: Callable[[], None] = _no_stop, grids: tuple[GridSpec, ...] = (GRID_PRESETS["occ3d"],),
                flow: bool | Collection[str] = False) -> tuple[Labels, SceneCounts]:
    """Labels of every keyframe of `scene` on each of `grids` from one aggregation: grid name -> sample
    token -> {"semantics"[, "mask_lidar", "mask_camera"]} `(X, Y, Z) uint8` in Occ3D classes (17 = free;
    the writers map them to the grid's ids), and the scene's point counts. `flow`: True for every grid,
    or the names of the grids whose labels also hold `flow (X, Y, Z, 2) float32`, the box velocity (m/s,
    grid frame) of their object voxels (`voxel_flow`; X*Y*Z*8 bytes a keyframe: 84 MB at 512x512x40).
    Every LiDAR of the rig is aggregated (each frame through its own calibration and ego pose); with
    carving (`LabelOptions.carves`) the points outside boxes are split by the scene's rays.
    `should_stop()` is called between frames (nothing is written here): it raises to stop the run."""
    sc = _start(inputs, scene, opts, grids, should_stop)
    cloud, rays, deferred, with_seg = _gather_keyframes(sc)
    _gather_sweeps(sc, cloud, deferred, with_seg)
    sc.counts.instances = len(cloud.obj_pts)
    return _keyframe_labels(sc, cloud, rays, grids, flow), sc.counts


def _start(inputs: LabelSources, scene: SceneRecord, opts: LabelOptions, grids: tuple[GridSpec, ...],
           should_stop: Callable[[], None]) -> _Scene:
    """The scene's mode (boxes, naive, carve, boxes+carve) and, when it is carved, its carve grid."""
    ds = inputs.dataset
    indices = [ds.index_of(t) for t in scene.sample_tokens]
    counts = SceneCounts(keyframes=len(indices))
    has_boxes = any(inputs.annotations.boxes_by_sample.get(t) for t in scene.sample_tokens)
    carving = opts.carves(has_boxes, len(indices))
    counts.mode = opts.mode(has_boxes, len(indices))
    track = scene_track(ds, indices) if opts.deskew else None
    carve_grid = None
    if carving:
        if len(indices) < 2:
            raise OccDataError(f"scene {scene.name} has {len(indices)} keyframe: too short to carve (carving needs "
                               "other times' rays); label it without --carve / --boxes none")
        frames = scene_frames(ds, indices, opts.all_sweeps)
        n_key = sum(len(ds.samples[i].lidars) for i in indices)
        carve_grid = carve_scene(frames, n_key, *carve_region([ds.samples[i] for i in indices], grids),
                                 opts.carve_options, should_stop, track)
        counts.carve_voxels = int(np.prod(carve_grid.shape))
    withheld = carving and not opts.use_boxes  # --boxes none: the boxes give nothing, not even classes
    classes = None if inputs.segmented else scene_classes(inputs, indices, opts, carve_grid, withheld, should_stop)
    return _Scene(inputs, opts, indices, counts, withheld, carve_grid, should_stop, track, classes)


def _gather_keyframes(sc: _Scene) -> tuple[Cloud, dict[str, Rays], list[Frame], bool]:
    """Pass 1, the keyframes (the labelled references): their points gathered into a new cloud, their rays
    per sample token, the keyframes left for pass 2 (with lidarseg, which labels the reference LiDAR alone,
    the other LiDARs' keyframes are labelled as sweeps) and whether any point had a lidarseg class."""
    ds, counts = sc.inputs.dataset, sc.counts
    cloud = Cloud()
    rays: dict[str, Rays] = {}
    deferred: list[Frame] = []
    with_seg = False
    for i in sc.indices:
        sc.should_stop()  # Ctrl-C / SIGTERM of an in-process run: stop between frames
        s = ds.samples[i]
        rays[s.token] = []
        for k, rec in enumerate(s.lidars):
            points, origin, off_ego = frame_points(rec, sc.track)
            rays[s.token].append((origin, points[off_ego]))
            if k > 0 and sc.inputs.segmented:
                deferred.append((i, k, rec))
                continue
            cls = keyframe_classes(sc.inputs, rec, len(points)) if k == 0 else None
            keep = off_ego if cls is None else off_ego & (cls != DROP)
            with_seg |= cls is not None
            counts.add_frame(len(points), int((~off_ego).sum()))
            counts.dropped_class += int((off_ego & ~keep).sum())
            boxes = sc.boxes(i, k, rec)
            add_keyframe(cloud, points[keep], None if cls is None else cls[keep], boxes, sc.opts, counts,
                         sc.moving(points[keep], cls is not None, rec.timestamp), rec.timestamp,
                         None if cls is not None else sc.own(points[keep], rec.timestamp, boxes))
    return cloud, rays, deferred, with_seg


def _gather_sweeps(sc: _Scene, cloud: Cloud, deferred: list[Frame], with_seg: bool) -> None:
    """Pass 2: the `deferred` keyframes and (`all_sweeps`) the sweeps, into `cloud`, each point labelled
    from the keyframes' (with lidarseg: the nearest labelled keyframe point's class, `add_sweep`)."""
    ds = sc.inputs.dataset
    sweeps = deferred
    if sc.opts.all_sweeps:
        sweeps = deferred + [f for f in scene_frames(ds, sc.indices, True) if f[2] not in ds.samples[f[0]].lidars]
    if not sweeps:
        return
    static_index = object_index = dynamic_index = None
    if with_seg:
        radius = sc.opts.knn_radius
        static_index = NearestIndex.build(*cloud.static(), radius)
        object_index = {k: NearestIndex.build(*cloud.instance(k), radius) for k in cloud.obj_pts}
        if sc.carve_grid is not None:
            dynamic_index = NearestIndex.build(*cloud.dynamic(), radius)
    for i, k, rec in sweeps:
        sc.should_stop()
        points, _, off_ego = frame_points(rec, sc.track)
        sc.counts.add_frame(len(points), int((~off_ego).sum()))
        boxes = sc.boxes(i, k, rec)
        add_sweep(cloud, points[off_ego], boxes, static_index, object_index or {}, sc.opts, sc.counts,
                  sc.moving(points[off_ego], False, rec.timestamp), rec.timestamp, dynamic_index,
                  sc.own(points[off_ego], rec.timestamp, boxes))


def _keyframe_labels(sc: _Scene, cloud: Cloud, rays: dict[str, Rays], grids: tuple[GridSpec, ...],
                     flow: bool | Collection[str]) -> Labels:
    """Every keyframe's labels on every grid (`grid_labels`): the static scene, each instance at its box
    there (parked instances held at their nearest pose, `held_static`) and the dynamic points near its
    time; flow on the grids named in `flow` (True: all)."""
    ds, opts = sc.inputs.dataset, sc.opts
    static = tuple(np.ascontiguousarray(a) for a in cloud.static())
    out: Labels = {spec.name: {} for spec in grids}
    keyframe_boxes = [sc.boxes(i, 0, ds.samples[i].lidar) for i in sc.indices]
    held = held_static(keyframe_boxes, opts.hold_static)
    flow_names = {spec.name for spec in grids} if flow is True else set(flow or ())
    v_global = box_velocities(sc.inputs, keyframe_boxes, held) if flow_names else []
    # Grids that differ only in classes and layout (occ3d and openocc-v2) share one voxelisation:
    # the stored ids are mapped when written. Computed once per keyframe, with what any of them needs.
    groups: dict[tuple[object, ...], list[GridSpec]] = {}
    for spec in grids:
        groups.setdefault((spec.grid, spec.frame), []).append(spec)
    ray_list = [rays[ds.samples[i].token] for i in sc.indices]
    for n, i in enumerate(sc.indices):
        s = ds.samples[i]
        boxes = keyframe_boxes[n] + held[n]
        more = static_rays(ray_list, n) if opts.densify else None
        dynamic = cloud.dynamic_at(s.timestamp, opts.carve_options.window) if sc.carve_grid is not None else None
        for members in groups.values():
            sc.should_stop()
            any_flow = any(g.name in flow_names for g in members)
            shared = grid_labels(static, cloud, boxes, s, rays[s.token], members[0],
                                 any(g.masks for g in members), v_global[n] if any_flow else None,
                                 more_rays=more, dynamic=dynamic, solids=sc.inputs.segmented,
                                 classes=sc.classes)
            for spec in members:
                keep = {"semantics", *(("mask_lidar", "mask_camera") if spec.masks else ()),
                        *(("flow",) if spec.name in flow_names else ())}
                out[spec.name][s.token] = {k: v for k, v in shared.items() if k in keep}
    return out
