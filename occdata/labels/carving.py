"""Carving over a scene: the free-space evidence (`occdata.labels.carve.CarveGrid`) of every LiDAR frame
of the scene, each ray from its own LiDAR's origin, counted once per time slot (one sweep of the rig,
`sweep_keys`); the keyframes' ground first (the slots' height errors and the ground map,
`occdata.labels.heights`)."""

from __future__ import annotations

from collections.abc import Callable
from itertools import groupby

import numpy as np

from occdata.errors import OccDataError
from occdata.formats.gridspec import GridSpec
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.carve import MAX_SLOTS, CarveGrid, CarveOptions, sweep_slots
from occdata.labels.deskew import PoseTrack
from occdata.labels.frames import Frame, T_grid_from_keyego, off_ego_rays
from occdata.labels.heights import GroundMap, HeightOffsets, ground_cells, ground_map, height_offsets
from occdata.nuscenes import SampleRecord

__all__ = ["carve_region", "carve_scene", "sweep_keys"]


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


def sweep_keys(frames: list[Frame], keyframe_frames: int) -> list[tuple[int, int]]:
    """Per frame (`scene_frames`' order, the first `keyframe_frames` the keyframes'), the sweep of the rig
    it belongs to: `(sample index, n)`, n = 0 for the sample's keyframes (every LiDAR's) and n for each
    LiDAR's n-th sweep before it (latest first). The key names sample_data, never a time window, so
    LiDARs that fire tens of ms apart make one slot, and two sweeps of one LiDAR never share one."""
    keys = [(i, 0) for i, _, _ in frames[:keyframe_frames]]
    sweeps = frames[keyframe_frames:]
    rank = [0] * len(sweeps)
    order = sorted(range(len(sweeps)), key=lambda f: (sweeps[f][0], sweeps[f][1], -sweeps[f][2].timestamp))
    for _, group in groupby(order, key=lambda f: sweeps[f][:2]):
        for n, f in enumerate(group, start=1):
            rank[f] = n
    return keys + [(i, n) for (i, _, _), n in zip(sweeps, rank, strict=True)]


def carve_scene(frames: list[Frame], keyframe_frames: int, lo: np.ndarray, hi: np.ndarray,
                opts: CarveOptions, should_stop: Callable[[], None], track: PoseTrack | None = None) -> CarveGrid:
    """The scene's free-space evidence (`occdata.labels.carve`): every frame's rays, from its own LiDAR,
    counted once per time slot (`sweep_keys`: a keyframe's LiDARs are one); `frames` as `scene_frames` gives them,
    the first `keyframe_frames` the keyframes' (the sweeps' rays are thinned, `CarveOptions.ray_stride`).
    The keyframes' ground comes first: the slots' height errors (`opts.align_heights`) and the ground map;
    the keyframes' points are then read once for both (a scene's keyframes: tens of MB). `track`: place
    points by their own times (`frame_points`)."""
    slots = sweep_slots(sweep_keys(frames, keyframe_frames), [rec.timestamp for _, _, rec in frames])
    if len(slots) and slots.max() >= MAX_SLOTS:
        raise OccDataError(f"{int(slots.max()) + 1:,} LiDAR sweeps in one scene: carving counts at most {MAX_SLOTS:,}; "
                           "label shorter scenes, or without --all-sweeps")
    key_rays: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    heights = ground = None
    if opts.align_heights or opts.ground_clearance > 0:
        key_rays = {f: off_ego_rays(frames[f][2], track) for f in range(keyframe_frames)}
        heights, ground = _slot_ground(key_rays, frames, slots, opts.align_heights, should_stop)
    grid = CarveGrid(lo, hi, opts, heights, ground)
    for slot in np.unique(slots):
        should_stop()
        members = np.flatnonzero(slots == slot)
        rays = [key_rays.pop(f) if f in key_rays else off_ego_rays(frames[f][2], track) for f in members]
        grid.add_slot(int(slot), rays, thin=bool(members.max() >= keyframe_frames),
                      t_us=frames[members[0]][2].timestamp)
    return grid


def _slot_ground(key_rays: dict[int, tuple[np.ndarray, np.ndarray]], frames: list[Frame],
                 slots: np.ndarray, align: bool,
                 should_stop: Callable[[], None]) -> tuple[HeightOffsets | None, GroundMap]:
    """The keyframe slots' height errors (`align`; else None) and the scene's ground map
    (`occdata.labels.heights`) from the ground columns of their frames `key_rays` (frame index ->
    `off_ego_rays`), each slot at its first frame's time and the origin of its first LiDAR. Slots are
    numbered in time order (`sweep_slots`), so their times increase."""
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
