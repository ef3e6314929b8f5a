"""Free-space carving: which LiDAR points were on something that moved, from the scene's own rays.

What a ray passes through was empty when it was cast. A point is **dynamic** when enough other frames'
rays passed through its place; the static scene is aggregated over time, a dynamic point is drawn only
at its own time (`occdata.labels.scene`). Evidence lives on a carve grid: an axis-aligned grid in the
global frame (`CarveGrid`, `voxel_size` metres, covering every keyframe's label grids), with per voxel

- `hits`: the number of **time slots** with a return in the voxel. A slot is one sweep of the rig,
  named by the sample_data its frames are (`sweep_slots`): a keyframe's LiDARs together, and the n-th
  sweep before that keyframe of each LiDAR together, however far apart the LiDARs fire;
- `crossed`: the number of time slots whose rays crossed the voxel **as evidence**, which leaves out
  1. the part of each ray within `graze` metres before its return, `graze = clamp(graze_height /
     |sin(elevation)|, margin, graze_max)`: a ray descending onto the ground at a grazing angle runs
     within `graze_height` of the ground's height over its last `graze_height / |sin|` metres and
     proves nothing about the ground's voxels there; `margin` (densify's `FREE_MARGIN`, 0.4 m) is the
     floor for steep rays, `graze_max` the cap for level ones;
  2. the voxels within `near` voxels (in x, y and z) of a return of the same time slot: a ray that
     passes that close to what its own slot hit runs along a surface (a wall seen at a slant, a
     kerb, leaves) and a few centimetres of pose or range error put it on either side of it (0: only
     the return's own voxel). Above a return on the ground (within `ground_clearance` of the scene's
     ground) the rule reaches `near_above_ground` voxels up, not `near`: rule 1 already leaves out a
     ray's descent onto the road, and shielding the voxels over every road return left the lowest
     half metre of each passing car static (real Lyft: 70% of the open-road smear that carving kept).

Before counting, each slot's frames are moved in height by the slot's error (`align_heights`,
`occdata.labels.heights`): nuScenes ego poses have z = 0, and frames that disagree by decimetres
about the ground's height carve each other's ground and walls.

A point is dynamic when its voxel has `crossed >= min_frames` and `crossed >= ratio * hits`: at least
`min_frames` other times saw its place empty, and at least as many (`ratio` 1) as saw something there;
with lidarseg a third as many (`ratio_seg`), since its ground, buildings and vegetation stay static.
It is also dynamic when at least `min_gone` slots saw its voxel empty **after the voxel's last return**
(`after`: what was there left) or **before its first** (`before`: it came). The ratio alone kept the
side of a long mover: a bus passing at 6.4 m/s fills a 0.3 m voxel of its side for about 38 sweeps,
and a short scene has fewer sweeps left to see the place empty (synthetic seed 23: 35% of the movers'
points kept static, most of them the bus's; 14% with `min_gone` 4). A static surface's stray
crossings fall between its returns, so they count in neither. Slots are added in time order.
A point within `ground_clearance` of the scene's ground (the lowest surface any keyframe saw in its
0.5 m column, `occdata.labels.heights.ground_map`) is never dynamic: the ground does not move, and a
voxel the ground only grazes (its points at the voxel's bottom) is crossed by rays that pass a few
centimetres over the road on their way to lower ground farther off.

Counts are exact: `uint16`, and a scene takes at most `MAX_SLOTS` (65,535) slots, each counted at
most once per voxel, so no count saturates (a 20 s scene with every sweep of a 20 Hz LiDAR has about
400; 65,535 are 55 minutes of it). Grids are `(X, Y, Z)`; `lower (3,) float64` the lower corner in global. Every
numba kernel here has a plain numpy twin in tests/reference/labels_carve.py, and a test that they agree.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from occdata.errors import OccDataError
from occdata.labels.densify import FREE_MARGIN
from occdata.labels.heights import GroundMap, HeightOffsets
from occdata.sensors.raycast import segment_advance, segment_setup

__all__ = ["MAX_SLOTS", "CarveGrid", "CarveOptions", "carve_rays", "dynamic_points", "mark_hits", "mark_near",
           "sweep_slots"]

# Above this many carve voxels (12 bytes each) a scene is refused rather than swapping.
MAX_VOXELS = 400_000_000
# The most time slots a scene may have: the counts' dtype holds this many, so none saturates.
MAX_SLOTS = int(np.iinfo(np.uint16).max)
_NONE = -1  # stamp of a voxel no slot has touched


@dataclass(frozen=True)
class CarveOptions:
    """The evidence rules of the module docstring (recorded in labels.json when carving is on).

    voxel_size: carve grid voxel (m). min_frames: time slots that must have seen a point's voxel empty.
    ratio: ... and at least this many times the slots that saw it occupied. ratio_seg: the same for
    points with a lidarseg class, whose ground, buildings and vegetation are never dynamic whatever
    the rays say (so a looser rule risks only objects). graze_height: the height over a return
    within which a descending ray is no evidence (m); margin / graze_max: the least and the most of
    each ray's last metres left out (m). near: voxels around a slot's returns that its rays give no
    evidence for; near_above_ground: of those, how many above a return on the ground (`near`: the
    rule before, the same all round). align_heights: move each slot's frames by its height error first
    (`occdata.labels.heights`). ground_clearance: points within this height over the scene's ground
    are static (m; 0: no ground rule). window: seconds either side of a keyframe within which dynamic points
    are drawn at it (its own sweep always; 0.055 s also takes the neighbouring sweeps of a 20 Hz
    LiDAR). min_gone: slots that saw a voxel empty before its first or after its last return that make
    its points dynamic whatever the ratio (0: no such rule).
    ray_stride: of a non-keyframe sweep cast every n-th ray (every return still counts as a
    hit): carving's cost is its rays' steps, and sweeps come 10 a keyframe. The voxel was chosen on
    the 40-keyframe synthetic world (docs/labels.md, "Without boxes"): 0.3 m voxels left 1,214 smear
    voxels against 1,510 at 0.2 m and 29,177 at 0.4 m."""

    voxel_size: float = 0.3
    min_frames: int = 2
    ratio: float = 1.0
    ratio_seg: float = 0.33
    margin: float = FREE_MARGIN
    graze_max: float = 5.0
    window: float = 0.055
    ray_stride: int = 2
    graze_height: float = 0.3
    near: int = 1
    near_above_ground: int = 0
    align_heights: bool = True
    ground_clearance: float = 0.2
    min_gone: int = 4

    def __post_init__(self) -> None:
        if not 0.05 <= self.voxel_size <= 2.0:
            raise ValueError("carve voxel_size must be in [0.05, 2] m")
        if not 1 <= self.min_frames <= MAX_SLOTS:
            raise ValueError(f"carve min_frames must be in [1, {MAX_SLOTS}]")
        if not 0 < self.ratio <= 100 or not 0 < self.ratio_seg <= 100:
            raise ValueError("carve ratio must be in (0, 100]")
        if not 0 <= self.margin <= self.graze_max <= 50:
            raise ValueError("carve margins need 0 <= margin <= graze_max <= 50 m")
        if not 0 <= self.window <= 5:
            raise ValueError("carve window must be in [0, 5] s")
        if not 1 <= self.ray_stride <= 64:
            raise ValueError("carve ray_stride must be in [1, 64]")
        if not 0 < self.graze_height <= 5:
            raise ValueError("carve graze_height must be in (0, 5] m")
        if not 0 <= self.ground_clearance <= 2:
            raise ValueError("carve ground_clearance must be in [0, 2] m")
        if not 0 <= self.near <= 3:
            raise ValueError("carve near must be 0, 1, 2 or 3 voxels")
        if not 0 <= self.min_gone <= MAX_SLOTS:
            raise ValueError(f"carve min_gone must be in [0, {MAX_SLOTS}]")
        if not 0 <= self.near_above_ground <= self.near:
            raise ValueError("carve near_above_ground must be in [0, near] voxels")


@njit(cache=True, inline="always")
def _voxel_of(point: np.ndarray, lower: np.ndarray, voxel_size: float) -> tuple[int, int, int]:
    """The voxel index of a point `(3,)` (may lie outside the grid: the callers test the bounds)."""
    return (int(np.floor((point[0] - lower[0]) / voxel_size)), int(np.floor((point[1] - lower[1]) / voxel_size)),
            int(np.floor((point[2] - lower[2]) / voxel_size)))


@njit(cache=True)
def mark_hits(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray, slot: int,
              hits: np.ndarray, stamp: np.ndarray, crossed: np.ndarray, before: np.ndarray,
              after: np.ndarray) -> None:
    """Count time slot `slot` once in `hits` (X, Y, Z) uint16 for each voxel holding a point of
    `points (N, 3) float64` (global); `stamp (X, Y, Z) int32` becomes `2 * slot` there (in place).
    Slots come in time order: at a voxel's first return `before` takes its `crossed` so far (the slots
    that saw it empty before anything was there), and every return sets `after` to 0 (`carve_rays`
    counts the slots that see it empty after its last return there)."""
    for n in range(points.shape[0]):
        i, j, k = _voxel_of(points[n], lower, voxel_size)
        if i < 0 or j < 0 or k < 0 or i >= shape[0] or j >= shape[1] or k >= shape[2]:
            continue
        if stamp[i, j, k] != 2 * slot:
            stamp[i, j, k] = 2 * slot
            if hits[i, j, k] == 0:
                before[i, j, k] = crossed[i, j, k]
            hits[i, j, k] += 1  # at most MAX_SLOTS slots (`CarveGrid.add_slot`): never wraps
            after[i, j, k] = 0


@njit(cache=True)
def mark_near(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray, slot: int, near: int,
              up: int, stamp: np.ndarray) -> None:
    """`stamp (X, Y, Z) int32` becomes `2 * slot` in every voxel within `near` voxels in x and y, and
    from `near` below to `up` above in z, of the voxel of a point of `points (N, 3) float64` (global):
    no evidence from this slot there. Run after every frame of the slot has gone through `mark_hits`
    (which counts a slot once per voxel by the same stamp)."""
    for n in range(points.shape[0]):
        i0, j0, k0 = _voxel_of(points[n], lower, voxel_size)
        for i in range(max(i0 - near, 0), min(i0 + near + 1, shape[0])):
            for j in range(max(j0 - near, 0), min(j0 + near + 1, shape[1])):
                for k in range(max(k0 - near, 0), min(k0 + up + 1, shape[2])):
                    stamp[i, j, k] = 2 * slot


@njit(cache=True)
def carve_rays(origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float,
               shape: np.ndarray, slot: int, margin: float, graze_max: float, graze_height: float,
               crossed: np.ndarray, stamp: np.ndarray, after: np.ndarray) -> None:
    """Count time slot `slot` once in `crossed (X, Y, Z) uint16` and in `after` (the same, reset by
    each return: `mark_hits`) for each voxel its rays `origins (N, 3)
    -> endpoints (N, 3)` (float64, global) cross as evidence (module docstring: the last `graze`
    metres and the return's voxel left out, and voxels where `stamp == 2 * slot`, i.e. this slot has a
    return there or near, skipped). The slot's hits must be marked first (`mark_hits`, `mark_near`);
    `stamp` becomes `2 * slot + 1` where counted."""
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
        graze = graze_max if sin * graze_max <= graze_height else graze_height / sin
        graze = max(graze, margin)
        if length <= graze:
            continue
        b = a + (e - a) * (1.0 - graze / length)
        ok, t_end = segment_setup(a, b, lower, voxel_size, shape, idx, step, t_next, t_delta)
        if not ok:
            continue
        while True:  # the return's own voxel needs no test: `mark_hits` stamped it `2 * slot`
            i, j, k = idx[0], idx[1], idx[2]
            if stamp[i, j, k] != 2 * slot and stamp[i, j, k] != 2 * slot + 1:
                stamp[i, j, k] = 2 * slot + 1
                crossed[i, j, k] += 1  # as `mark_hits`: never wraps
                after[i, j, k] += 1
            if segment_advance(idx, step, t_next, t_delta, shape) > t_end:
                break


@njit(cache=True)
def dynamic_points(points: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
                   hits: np.ndarray, crossed: np.ndarray, min_frames: int, ratio: float,
                   before: np.ndarray, after: np.ndarray, min_gone: int) -> np.ndarray:
    """`(N,) bool`: points `(N, 3) float64` (global) whose voxel has `crossed >= min_frames` and
    `crossed >= ratio * hits`, or (`min_gone` > 0) `before >= min_gone` or `after >= min_gone`;
    False outside the grid."""
    out = np.zeros(points.shape[0], np.bool_)
    for n in range(points.shape[0]):
        i, j, k = _voxel_of(points[n], lower, voxel_size)
        if i < 0 or j < 0 or k < 0 or i >= shape[0] or j >= shape[1] or k >= shape[2]:
            continue
        c = crossed[i, j, k]
        gone = min_gone > 0 and hits[i, j, k] > 0 and (before[i, j, k] >= min_gone or after[i, j, k] >= min_gone)
        out[n] = (c >= min_frames and c >= ratio * hits[i, j, k]) or gone
    return out


def sweep_slots(keys: Sequence[Hashable], timestamps_us: Sequence[int]) -> np.ndarray:
    """`(F,) int64` slot of each frame: frames of equal `keys` (one sweep of the rig, e.g. a keyframe's
    LiDARs: `occdata.labels.carving.sweep_keys`) share one, whatever their times; slots are numbered
    in the time order of their first frames (ties: first given first)."""
    t = np.asarray(timestamps_us, np.int64)
    first: dict[Hashable, int] = {}
    for f in np.argsort(t, kind="stable"):
        first.setdefault(keys[f], len(first))
    return np.array([first[k] for k in keys], np.int64).reshape(len(keys))


class CarveGrid:
    """The evidence of one scene (module docstring): `hits`, `crossed`, `before`, `after` `(X, Y, Z) uint16`
    and a stamp, on the axis-aligned global box `[lo, hi]` (m) at `opts.voxel_size`, grown in height by the largest
    of `heights` (each frame's height error, `occdata.labels.heights`; zero: none); `ground`: the
    scene's ground map in aligned heights (None: no ground rule). Feed every time
    slot once, in time order (`add_slot`: all of its frames together), then ask `dynamic(points, t_us)`."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, opts: CarveOptions,
                 heights: HeightOffsets | None = None, ground: GroundMap | None = None) -> None:
        self.opts = opts
        self.heights = heights or HeightOffsets.zero()
        self.ground = ground
        grow = np.array([0.0, 0.0, float(np.abs(self.heights.dz).max())])
        self.lower = np.asarray(lo, np.float64) - grow
        extent = np.asarray(hi, np.float64) + grow - self.lower
        self.shape = np.maximum(np.ceil(extent / opts.voxel_size), 1).astype(np.int64)
        n = int(np.prod(self.shape))
        if n > MAX_VOXELS:
            raise OccDataError(f"carve grid of {n:,} voxels ({self.shape.tolist()}) is too large for this scene's "
                               f"extent; use a larger carve voxel than {opts.voxel_size} m")
        self.hits = np.zeros(tuple(self.shape), np.uint16)
        self.crossed = np.zeros(tuple(self.shape), np.uint16)
        self.before = np.zeros(tuple(self.shape), np.uint16)
        self.after = np.zeros(tuple(self.shape), np.uint16)
        self.stamp = np.full(tuple(self.shape), _NONE, np.int32)
        self._slots: set[int] = set()

    def _aligned(self, points: np.ndarray, t_us: int) -> np.ndarray:
        """`points (N, 3)` (global) less the height error at `t_us`, `(N, 3) float64` contiguous."""
        out = np.array(points, np.float64).reshape(-1, 3)
        out[:, 2] -= self.heights.at(t_us)
        return out

    def add_slot(self, slot: int, rays: Iterable[tuple[np.ndarray, np.ndarray]], thin: bool = False,
                 t_us: int = 0) -> None:
        """One time slot's frames, taken at `t_us`: `(origin (3,), points (N, 3))` float64 in global,
        points off the ego; `thin`: cast every `ray_stride`-th ray only (sweeps)."""
        if (self._slots and slot <= max(self._slots)) or not 0 <= slot < MAX_SLOTS:
            raise ValueError(f"time slot {slot} given twice or out of time order (or not in [0, {MAX_SLOTS}))")
        self._slots.add(slot)
        rays = [(self._aligned(o, t_us)[0], self._aligned(p, t_us)) for o, p in rays]
        v = float(self.opts.voxel_size)
        for _, pts in rays:
            mark_hits(pts, self.lower, v, self.shape, slot, self.hits, self.stamp, self.crossed, self.before,
                      self.after)
        near, up = int(self.opts.near), int(self.opts.near_above_ground)
        if near:
            for _, pts in rays:
                on_ground = self.on_ground(pts) if up < near else np.zeros(len(pts), bool)
                mark_near(np.ascontiguousarray(pts[~on_ground]), self.lower, v, self.shape, slot, near, near,
                          self.stamp)
                mark_near(np.ascontiguousarray(pts[on_ground]), self.lower, v, self.shape, slot, near, up, self.stamp)
        for origin, pts in rays:
            pts = np.ascontiguousarray(pts[::self.opts.ray_stride] if thin else pts)
            origins = np.ascontiguousarray(np.broadcast_to(origin, pts.shape))
            carve_rays(origins, pts, self.lower, v, self.shape, slot, float(self.opts.margin),
                       float(self.opts.graze_max), float(self.opts.graze_height), self.crossed, self.stamp,
                       self.after)

    def dynamic(self, points: np.ndarray, t_us: int = 0, classified: bool = False) -> np.ndarray:
        """`(N,) bool`: which of `points (N, 3)` (global, of a frame taken at `t_us`) are dynamic
        (`dynamic_points`; `classified`: the points have lidarseg classes, `ratio_seg` applies)."""
        ratio = self.opts.ratio_seg if classified else self.opts.ratio
        pts = self._aligned(points, t_us)
        out = dynamic_points(pts, self.lower, float(self.opts.voxel_size), self.shape, self.hits, self.crossed,
                             int(self.opts.min_frames), float(ratio), self.before, self.after,
                             int(self.opts.min_gone))
        return out & ~self.on_ground(pts)

    def on_ground(self, points_aligned: np.ndarray) -> np.ndarray:
        """`(N,) bool`: which of `points_aligned (N, 3)` (global, heights aligned) lie within
        `ground_clearance` of the scene's ground; none without a ground rule or where no slot saw the
        column's ground."""
        if self.ground is None or self.opts.ground_clearance <= 0:
            return np.zeros(len(points_aligned), bool)
        with np.errstate(invalid="ignore"):  # NaN: no ground seen, False
            return points_aligned[:, 2] - self.ground.height_under(points_aligned) <= self.opts.ground_clearance

    @property
    def nbytes(self) -> int:
        return self.hits.nbytes + self.crossed.nbytes + self.before.nbytes + self.after.nbytes + self.stamp.nbytes
