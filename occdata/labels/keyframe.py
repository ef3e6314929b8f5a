"""One keyframe's labels on one grid, from a scene's gathered points (`occdata.labels.cloud`): the
static points plus each instance's points placed at that keyframe's box pose, majority vote per voxel
(`votes`); optionally densified (`densify_keyframe`); then `mask_lidar` / `mask_camera` from
occdata.visibility (`keyframe_masks`) and the flow of object voxels (`occdata.labels.flow`)."""

from __future__ import annotations

import numpy as np

from occdata.constants import FREE_LABEL, NUM_CLASSES, OccGrid
from occdata.formats.gridspec import GridSpec
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.boxes import box_class
from occdata.labels.cloud import Cloud
from occdata.labels.densify import densify
from occdata.labels.flow import voxel_flow
from occdata.labels.frames import Rays, T_grid_from_keyego, rays_in
from occdata.labels.kernels import majority, vote_voxels
from occdata.labels.semantics import SceneClasses
from occdata.nuscenes import SampleRecord
from occdata.nuscenes.annotations import BoxRecord
from occdata.visibility import camera_mask, lidar_mask

__all__ = ["STATIC_RAY_FRAMES", "densify_keyframe", "grid_labels", "keyframe_masks", "static_rays", "votes"]

# Densification casts about this many keyframes' worth of other keyframes' rays (`static_rays`).
STATIC_RAY_FRAMES = 8


def votes(static: tuple[np.ndarray, np.ndarray], cloud: Cloud, boxes: tuple[BoxRecord, ...],
          T_grid_from_global: np.ndarray, grid: OccGrid, dynamic: tuple[np.ndarray, np.ndarray] | None = None,
          n: int = NUM_CLASSES - 1) -> tuple[list[np.ndarray], list[int]]:
    """`vote_voxels` keys on `grid` of the static points (first; with them the keyframe's `dynamic`
    points, global, where they were then: they have no box, so no flow) and of each box's instance
    points placed at that box's pose (then one list per box with points), and the index in `boxes` of
    each list after the first. `n`: the classes a key holds (34 with two tiers, `occdata.labels.flat`)."""
    shape = np.array(grid.shape, np.int64)
    lower = np.array(grid.lower, np.float64)
    out = [vote_voxels(static[0], static[1], T_grid_from_global, lower, grid.voxel_size, shape, n)]
    if dynamic is not None and len(dynamic[0]):
        out[0] = np.concatenate([out[0], vote_voxels(np.ascontiguousarray(dynamic[0]), dynamic[1],
                                                     T_grid_from_global, lower, grid.voxel_size, shape, n)])
    box_of_vote = []
    for b, box in enumerate(boxes):  # (none placed in the control: it has no instance points)
        pts, cls = cloud.instance(box.instance_token)
        if len(pts):
            T = T_grid_from_global @ box.T_global_from_box()
            out.append(vote_voxels(np.ascontiguousarray(pts), cls, T, lower, grid.voxel_size, shape, n))
            box_of_vote.append(b)
    return out, box_of_vote


def keyframe_masks(semantics: np.ndarray, sample: SampleRecord, rays: Rays, spec: GridSpec) -> tuple[np.ndarray, ...]:
    """`mask_lidar`, `mask_camera` `(X, Y, Z) uint8` of a keyframe on `spec`'s grid: the keyframe's rays of
    every LiDAR (`Rays`, each from its own origin) traversed, plus every occupied voxel (their points
    were observed, by some frame); the camera mask within it (occdata.visibility)."""
    lower = np.array(spec.grid.lower, np.float64)
    T_grid_from_key = T_grid_from_keyego(sample, spec)
    T_grid_from_global = T_grid_from_key @ invert_rigid(sample.T_global_from_keyego)
    origins, ends = rays_in(T_grid_from_global, rays)
    m_lidar = lidar_mask(semantics, origins, ends, lower, spec.grid.voxel_size) | (semantics != FREE_LABEL)
    m_lidar = m_lidar.astype(np.uint8)
    rig = sample.camera_rig()
    T_cam_from_grid = rig.T_cam_from_keyego @ invert_rigid(T_grid_from_key)
    return m_lidar, camera_mask(semantics, m_lidar, rig.K, T_cam_from_grid, rig.image_size, lower,
                                spec.grid.voxel_size)


def static_rays(rays: list[Rays], n: int, budget: int = STATIC_RAY_FRAMES) -> tuple[np.ndarray, np.ndarray]:
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


def densify_keyframe(semantics: np.ndarray, vote_lists: list[np.ndarray], box_of_vote: list[int],
                     boxes: tuple[BoxRecord, ...], rays: Rays, T_grid_from_global: np.ndarray, grid: OccGrid,
                     more_rays: tuple[np.ndarray, np.ndarray], solids: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """`densify` of one keyframe's `semantics` with its rays (global) and the boxes whose instance votes
    in this grid (an object is filled only where its points are seen), and `more_rays` (global; other
    keyframes' rays, `static_rays`) as evidence for the static scene; `solids`: the static classes are
    lidarseg's (else no walk behind surfaces, `densify`): the new semantics, and `(X, Y, Z) int64` the index
    in `boxes` of the box that filled each voxel (-1: none)."""
    seen = [box_of_vote[m] for m in range(len(box_of_vote)) if len(vote_lists[m + 1])]
    T = np.array([invert_rigid(T_grid_from_global @ boxes[b].T_global_from_box()) for b in seen]).reshape(-1, 4, 4)
    half = np.array([[boxes[b].size_wlh[1] / 2, boxes[b].size_wlh[0] / 2, boxes[b].size_wlh[2] / 2] for b in seen])
    cls = np.array([box_class(boxes[b]) for b in seen], np.uint8)
    more = tuple(transform_points(T_grid_from_global, a) for a in more_rays)
    if len(rays) == 1:  # as before several LiDARs were read (byte-identical)
        origin = transform_points(T_grid_from_global, rays[0][0][None])[0]
        ends = transform_points(T_grid_from_global, rays[0][1])
    else:  # each ray from its own LiDAR; the walks behind surfaces start from the reference LiDAR
        origin, ends = rays_in(T_grid_from_global, rays)
    dense, owner = densify(semantics, origin, ends, T, half.reshape(-1, 3),
                           cls, np.array(grid.lower, np.float64), grid.voxel_size, more, solids)
    return dense, np.where(owner >= 0, np.append(np.asarray(seen, np.int64), -1)[owner], -1)


def grid_labels(static: tuple[np.ndarray, np.ndarray], cloud: Cloud, boxes: tuple[BoxRecord, ...],
                sample: SampleRecord, rays: Rays, spec: GridSpec,
                masks: bool, v_global: np.ndarray | None = None,
                more_rays: tuple[np.ndarray, np.ndarray] | None = None,
                dynamic: tuple[np.ndarray, np.ndarray] | None = None, solids: bool = True,
                classes: SceneClasses | None = None) -> dict[str, np.ndarray]:
    """One keyframe on one grid: `semantics` in Occ3D classes (17 = free) and, with `masks`, the masks;
    all `(X, Y, Z) uint8` in the grid's frame. With `v_global (B, 3)` (m/s, global, one row per box of
    `boxes`, NaN as 0) also `flow (X, Y, Z, 2) float32` (`voxel_flow`). With `more_rays` (`static_rays`),
    `densify_keyframe` the semantics before the masks (a voxel a box filled takes its flow). `dynamic`: the
    keyframe's dynamic points and classes (carving; global). `classes`: the ground and masks of a scene
    without lidarseg (`occdata.labels.semantics`; None: a plain majority)."""
    T = T_grid_from_keyego(sample, spec) @ invert_rigid(sample.T_global_from_keyego)
    if classes is None:
        vote_lists, box_of_vote = votes(static, cloud, boxes, T, spec.grid, dynamic)
        semantics = majority(vote_lists, spec.grid.shape, NUM_CLASSES - 1, FREE_LABEL)
    else:
        vote_lists, box_of_vote = votes(static, cloud, boxes, T, spec.grid, dynamic, classes.n)
        semantics, vote_lists = classes.semantics(vote_lists, spec.grid.shape)
    filled_by = None
    if more_rays is not None:
        semantics, filled_by = densify_keyframe(semantics, vote_lists, box_of_vote, boxes, rays, T, spec.grid,
                                                more_rays, solids)
    out = {"semantics": semantics}
    if masks:
        out["mask_lidar"], out["mask_camera"] = keyframe_masks(semantics, sample, rays, spec)
    if v_global is not None:
        out["flow"] = voxel_flow(vote_lists, box_of_vote, semantics, v_global, T[:3, :3], filled_by)
    return out
