"""Free-space carving: which LiDAR points were on something that moved, from the scene's own rays.

What a ray passes through was empty when it was cast. A point is **dynamic** when enough other frames'
rays passed through its place; the static scene is aggregated over time, a dynamic point is drawn only
at its own time (`occdata.labels.scene`). Evidence lives on a carve grid: an axis-aligned grid in the
global frame (`CarveGrid`, `voxel_size` metres, covering every keyframe's label grids), with per voxel

- `hits`: the number of **time slots** (frames fired at the same time: a keyframe's LiDARs) with a
  return in the voxel;
- `crossed`: the number of time slots whose rays crossed the voxel **as evidence**, which leaves out
  1. the part of each ray within `graze` metres before its return, `graze = clamp(voxel_size /
     |sin(elevation)|, margin, graze_max)`: a ray descending onto the ground at a grazing angle runs
     through the ground's own voxels over its last `voxel_size / |sin|` metres (it is within one
     voxel height of its return's height there) and proves nothing about them; `margin` (densify's
     `FREE_MARGIN`, 0.4 m) is the floor for steep rays, `graze_max` the cap for level ones;
  2. the voxel holding the return itself;
  3. a voxel where the same time slot also has a return (it was seen occupied and crossed at once:
     partly filled, or a ray grazing it; no evidence either way).

A point is dynamic when its voxel has `crossed >= min_frames` and `crossed >= ratio * hits`: at least
`min_frames` other times saw its place empty, and at least as many (`ratio` 1) as saw something there;
with lidarseg a third as many (`ratio_seg`), since its ground, buildings and vegetation stay static.
Counts saturate at 255. Grids are `(X, Y, Z)`; `lower (3,) float64` the lower corner in global. Every
numba kernel here has a plain numpy twin in tests/reference/labels_carve.py, and a test that they agree.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from occdata.errors import OccDataError
from occdata.labels.densify import FREE_MARGIN
from occdata.sensors.raycast import segment_advance, segment_setup

__all__ = ["CarveGrid", "CarveOptions", "carve_rays", "dynamic_points", "mark_hits", "time_slots"]

# Above this many carve voxels (6 bytes each) a scene is refused rather than swapping.
MAX_VOXELS = 400_000_000
_NONE = -1  # stamp of a voxel no slot has touched


@dataclass(frozen=True)
class CarveOptions:
    """The evidence rules of the module docstring (recorded in labels.json when carving is on).

    voxel_size: carve grid voxel (m). min_frames: time slots that must have seen a point's voxel empty.
    ratio: ... and at least this many times the slots that saw it occupied. ratio_seg: the same for
    points with a lidarseg class, whose ground, buildings and vegetation are never dynamic whatever
    the rays say (so a looser rule risks only objects). margin / graze_max: the
    least and the most of each ray's last metres left out (m). window: seconds either side of a
    keyframe within which dynamic points are drawn at it (its own sweep always; 0.055 s also takes
    the neighbouring sweeps of a 20 Hz LiDAR). ray_stride: of a non-keyframe sweep cast every n-th ray
    (every return still counts as a hit): carving's cost is its rays' steps, and sweeps come 10 a
    keyframe. Chosen on the 40-keyframe synthetic world (docs/labels.md, "Without boxes"): 0.3 m
    voxels left 1,214 smear voxels against 1,510 at 0.2 m and 29,177 at 0.4 m."""

    voxel_size: float = 0.3
    min_frames: int = 2
    ratio: float = 1.0
    ratio_seg: float = 0.33
    margin: float = FREE_MARGIN
    graze_max: float = 5.0
    window: float = 0.055
    ray_stride: int = 2

    def __post_init__(self) -> None:
        if not 0.05 <= self.voxel_size <= 2.0:
            raise ValueError("carve voxel_size must be in [0.05, 2] m")
        if not 1 <= self.min_frames <= 255:
            raise ValueError("carve min_frames must be in [1, 255]")
        if not 0 < self.ratio <= 100 or not 0 < self.ratio_seg <= 100:
            raise ValueError("carve ratio must be in (0, 100]")
        if not 0 <= self.margin <= self.graze_max <= 50:
            raise ValueError("carve margins need 0 <= margin <= graze_max <= 50 m")
        if not 0 <= self.window <= 5:
            raise ValueError("carve window must be in [0, 5] s")
        if not 1 <= self.ray_stride <= 64:
            raise ValueError("carve ray_stride must be in [1, 64]")


@njit(cache=True, inline="always")
def _voxel_of(point: np.ndarray, lower: np.ndarray, voxel_size: float) -> tuple[int, int, int]:
    """The voxel index of a point `(3,)` (may lie outside the grid: the callers test the bounds)."""
    return (int(np.floor((point[0] - lower[0]) / voxel_size)), int(np.floor((point[1] - lower[1]) / voxel_size)),
            int(np.floor((point[2] - lower[2]) / voxel_size)))


@njit(cache=True)
def mark_hits(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray, slot: int,
              hits: np.ndarray, stamp: np.ndarray) -> None:
    """Count time slot `slot` once in `hits` (X, Y, Z) uint8 for each voxel holding a point of
    `points (N, 3) float64` (global); `stamp (X, Y, Z) int32` becomes `2 * slot` there (in place)."""
    for n in range(points.shape[0]):
        i, j, k = _voxel_of(points[n], lower, voxel_size)
        if i < 0 or j < 0 or k < 0 or i >= shape[0] or j >= shape[1] or k >= shape[2]:
            continue
        if stamp[i, j, k] != 2 * slot:
            stamp[i, j, k] = 2 * slot
            if hits[i, j, k] < 255:
                hits[i, j, k] += 1


@njit(cache=True)
def carve_rays(origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float,
               shape: np.ndarray, slot: int, margin: float, graze_max: float, crossed: np.ndarray,
               stamp: np.ndarray) -> None:
    """Count time slot `slot` once in `crossed (X, Y, Z) uint8` for each voxel its rays `origins (N, 3)
    -> endpoints (N, 3)` (float64, global) cross as evidence (module docstring: the last `graze`
    metres and the return's voxel left out, and voxels where `stamp == 2 * slot`, i.e. this slot has a
    return, skipped). The slot's hits must be marked first (`mark_hits`); `stamp` becomes `2 * slot + 1`
    where counted."""
    idx = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_next = np.empty(3)
    t_delta = np.empty(3)
    for n in range(origins.shape[0]):
        a, e = origins[n], endpoints[n]
        length = np.sqrt(((e - a) ** 2).sum())
        if length == 0.0:
            continue
        sin = abs(e[2] - a[2]) / length
        graze = graze_max if sin * graze_max <= voxel_size else voxel_size / sin
        graze = max(graze, margin)
        if length <= graze:
            continue
        b = a + (e - a) * (1.0 - graze / length)
        ok, t_end = segment_setup(a, b, lower, voxel_size, shape, idx, step, t_next, t_delta)
        if not ok:
            continue
        end = np.floor((e - lower) / voxel_size)
        while True:
            i, j, k = idx[0], idx[1], idx[2]
            if (i != end[0] or j != end[1] or k != end[2]) and stamp[i, j, k] != 2 * slot \
                    and stamp[i, j, k] != 2 * slot + 1:
                stamp[i, j, k] = 2 * slot + 1
                if crossed[i, j, k] < 255:
                    crossed[i, j, k] += 1
            if segment_advance(idx, step, t_next, t_delta, shape) > t_end:
                break


@njit(cache=True)
def dynamic_points(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
                   hits: np.ndarray, crossed: np.ndarray, min_frames: int, ratio: float) -> np.ndarray:
    """`(N,) bool`: points `(N, 3) float64` (global) whose voxel has `crossed >= min_frames` and
    `crossed >= ratio * hits`; False outside the grid."""
    out = np.zeros(points.shape[0], np.bool_)
    for n in range(points.shape[0]):
        i, j, k = _voxel_of(points[n], lower, voxel_size)
        if i < 0 or j < 0 or k < 0 or i >= shape[0] or j >= shape[1] or k >= shape[2]:
            continue
        c = crossed[i, j, k]
        out[n] = c >= min_frames and c >= ratio * hits[i, j, k]
    return out


def time_slots(timestamps_us: Sequence[int], tolerance_us: int = 10_000) -> np.ndarray:
    """`(F,) int64` slot of each frame: frames within `tolerance_us` of a slot's first frame (in time
    order) share it, so a keyframe's LiDARs, fired together, are one time."""
    t = np.asarray(timestamps_us, np.int64)
    out = np.empty(len(t), np.int64)
    slot, start = -1, None
    for f in np.argsort(t, kind="stable"):
        if start is None or t[f] - start > tolerance_us:
            slot, start = slot + 1, t[f]
        out[f] = slot
    return out


class CarveGrid:
    """The evidence of one scene (module docstring): `hits`, `crossed` `(X, Y, Z) uint8` and a stamp,
    on the axis-aligned global box `[lo, hi]` (m) at `opts.voxel_size`. Feed every time slot once, in
    any order (`add_slot`: all of its frames together), then ask `dynamic(points)`."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, opts: CarveOptions) -> None:
        self.opts = opts
        self.lower = np.asarray(lo, np.float64)
        extent = np.asarray(hi, np.float64) - self.lower
        self.shape = np.maximum(np.ceil(extent / opts.voxel_size), 1).astype(np.int64)
        n = int(np.prod(self.shape))
        if n > MAX_VOXELS:
            raise OccDataError(f"carve grid of {n:,} voxels ({self.shape.tolist()}) is too large for this scene's "
                               f"extent; use a larger carve voxel than {opts.voxel_size} m")
        self.hits = np.zeros(tuple(self.shape), np.uint8)
        self.crossed = np.zeros(tuple(self.shape), np.uint8)
        self.stamp = np.full(tuple(self.shape), _NONE, np.int32)
        self._slots: set[int] = set()

    def add_slot(self, slot: int, rays: Iterable[tuple[np.ndarray, np.ndarray]], thin: bool = False) -> None:
        """One time slot's frames: `(origin (3,), points (N, 3))` float64 in global, points off the ego;
        `thin`: cast every `ray_stride`-th ray only (sweeps)."""
        if slot in self._slots or slot < 0:
            raise ValueError(f"time slot {slot} given twice (or negative)")
        self._slots.add(slot)
        rays = [(np.asarray(o, np.float64), np.ascontiguousarray(p, np.float64).reshape(-1, 3)) for o, p in rays]
        v = float(self.opts.voxel_size)
        for _, pts in rays:
            mark_hits(pts, self.lower, v, self.shape, slot, self.hits, self.stamp)
        for origin, pts in rays:
            pts = np.ascontiguousarray(pts[::self.opts.ray_stride] if thin else pts)
            origins = np.ascontiguousarray(np.broadcast_to(origin, pts.shape))
            carve_rays(origins, pts, self.lower, v, self.shape, slot, float(self.opts.margin),
                       float(self.opts.graze_max), self.crossed, self.stamp)

    def dynamic(self, points: np.ndarray, classified: bool = False) -> np.ndarray:
        """`(N,) bool`: which of `points (N, 3)` (global) are dynamic (`dynamic_points`; `classified`:
        the points have lidarseg classes, `ratio_seg` applies)."""
        pts = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        ratio = self.opts.ratio_seg if classified else self.opts.ratio
        return dynamic_points(pts, self.lower, float(self.opts.voxel_size), self.shape, self.hits, self.crossed,
                              int(self.opts.min_frames), float(ratio))

    @property
    def nbytes(self) -> int:
        return self.hits.nbytes + self.crossed.nbytes + self.stamp.nbytes
