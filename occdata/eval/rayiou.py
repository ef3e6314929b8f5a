"""RayIoU (SparseOcc protocol): rays from up to 8 LiDAR origins per sample cast through truth and
prediction (3D DDA, `first_hits`); per-class ray counts summed over a split (no torch).

Definitions are in docs/design.md#metrics and docs/metrics.md. `RayIoUAccumulator` keeps its whole state in one
int64 array (`state`), so ranks/processes can sum it. Values are fractions in [0, 1].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from occdata.constants import FREE_LABEL, GRID, NUM_CLASSES, OccGrid
from occdata.errors import OccDataError
from occdata.eval.miou import _as_labels, _nanmean, _ratio

__all__ = [
    "RAYIOU_TAUS",
    "RayIoUAccumulator",
    "RayIoUResult",
    "first_hit_voxels",
    "first_hits",
    "lidar_ray_directions",
    "ray_counts",
    "ray_origins_keyego",
    "ray_pitches",
]

RAYIOU_TAUS: tuple[float, ...] = (1.0, 2.0, 4.0)
MAX_ORIGINS = 8
ORIGIN_MAX_XY = 39.0  # metres; origins outside |x| < 39 and |y| < 39 are not used
_MAX_STEPS = 1000  # the reference's traversal cap (a ray from inside the grid needs at most X + Y + Z)


# --------------------------------------------------------------------------------------------------
# RayIoU: rays, origins
# --------------------------------------------------------------------------------------------------
def ray_pitches() -> list[float]:
    """The 39 pitch angles (rad) of the query rays, lowest first (docs/design.md#metrics).

    -(pi/2 - atan(k + 1)) for k = 0..9, then the last step repeated until the pitch reaches 0.21
    (the nuScenes LiDAR's upper field of view)."""
    p = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while p[-1] < 0.21:
        p.append(p[-1] + (p[-1] - p[-2]))
    return p


def lidar_ray_directions() -> np.ndarray:
    """Unit query-ray directions `(14040, 3) float32` (x, y, z in the origin's ego axes).

    Pitch-major: ray `p * 360 + a` has pitch `ray_pitches()[p]` and azimuth `a` degrees (from +x
    towards +y)."""
    pitch = np.asarray(ray_pitches(), np.float64)[:, None]
    az = np.deg2rad(np.arange(0, 360, 1))[None, :]
    d = np.stack([np.cos(pitch) * np.cos(az), np.cos(pitch) * np.sin(az), np.sin(pitch) * np.ones_like(az)], -1)
    return d.reshape(-1, 3).astype(np.float32)


_RAYS: np.ndarray | None = None


def _rays() -> np.ndarray:
    global _RAYS
    if _RAYS is None:
        _RAYS = lidar_ray_directions()
        _RAYS.setflags(write=False)
    return _RAYS


def ray_origins_keyego(T_global_from_keyego: np.ndarray, T_ego_from_lidar: np.ndarray, current: int,
                       max_origins: int = MAX_ORIGINS, max_xy: float = ORIGIN_MAX_XY) -> np.ndarray:
    """RayIoU query origins for keyframe `current` of a scene, `(n, 3) float64` in its key ego.

    `T_global_from_keyego (S, 4, 4)`, `T_ego_from_lidar (S, 4, 4)`: every keyframe of the scene in
    time order. Each keyframe's LiDAR origin is moved into the current LiDAR frame through global,
    rounded to float32 (as the reference does), then into the current key ego; origins with
    |x| < max_xy and |y| < max_xy are kept (time order) and, if more than `max_origins` remain,
    the ones at np.round(np.linspace(0, n - 1, max_origins)) are used.
    """
    T_g = np.asarray(T_global_from_keyego, np.float64)
    T_el = np.asarray(T_ego_from_lidar, np.float64)
    if T_g.ndim != 3 or T_g.shape[1:] != (4, 4) or T_el.shape != T_g.shape:
        raise OccDataError(f"poses must be (S, 4, 4) arrays of equal shape, got {T_g.shape} and {T_el.shape}")
    if not 0 <= current < T_g.shape[0]:
        raise OccDataError(f"current keyframe {current} out of range for a scene of {T_g.shape[0]}")
    T_global_from_lidar = T_g @ T_el
    T_curlidar_from_global = np.linalg.inv(T_global_from_lidar[current])
    kept = []
    for s in range(T_g.shape[0]):
        if s == current:
            p_lidar = np.zeros(3, np.float32)
        else:
            p_lidar = (T_curlidar_from_global @ T_global_from_lidar[s])[:3, 3].astype(np.float32)
        p_h = np.ones(4)
        p_h[:3] = p_lidar
        p_ego = T_el[current, :3] @ p_h  # (3, 4) @ homogeneous point, as the reference does
        if abs(p_ego[0]) < max_xy and abs(p_ego[1]) < max_xy:
            kept.append(p_ego)
    if not kept:
        return np.zeros((0, 3), np.float64)
    out = np.stack(kept)
    if len(out) > max_origins:
        out = out[np.round(np.linspace(0, len(out) - 1, max_origins)).astype(np.int64)]
    return out


# --------------------------------------------------------------------------------------------------
# RayIoU: ray casting (3D DDA)
# --------------------------------------------------------------------------------------------------
def _ray_setup(origins_keyego: np.ndarray, directions: np.ndarray, grid: OccGrid) -> tuple[np.ndarray, np.ndarray]:
    """Origins `(n, 3)` and ray end points `(n, R, 3)` in voxel units, float32 (as the reference
    feeds its kernel: metres shifted by the grid's lower corner, divided by float32 voxel size)."""
    vs = float(np.float32(grid.voxel_size))
    lower = np.asarray(grid.lower, np.float64)
    o = np.asarray(origins_keyego, np.float64).reshape(-1, 3)
    o_v = ((o - lower) / vs).astype(np.float32)
    e_v = ((o[:, None, :] + directions.astype(np.float64)[None]) - lower) / vs
    return o_v, e_v.astype(np.float32)


@njit(cache=True, inline="always")
def _cast_one(labels: np.ndarray, free_label: int, ox: float, oy: float, oz: float,
              ex: float, ey: float, ez: float) -> tuple[float, int, int]:
    """First occupied voxel along the ray from o towards e (voxel units, float64 values of the
    reference's float32 inputs). Returns (distance where the ray leaves that voxel, its label, its
    flat index `(x * Y + y) * Z + z`), or (nan, free_label, -1) if the ray leaves the grid without a hit."""
    X, Y, Z = labels.shape
    rx, ry, rz = ex - ox, ey - oy, ez - oz
    n = math.sqrt(rx * rx + ry * ry + rz * rz)
    dx, dy, dz = rx / n, ry / n, rz / n
    vx, vy, vz = int(math.floor(ox)), int(math.floor(oy)), int(math.floor(oz))
    sx = 1 if dx >= 0 else -1
    sy = 1 if dy >= 0 else -1
    sz = 1 if dz >= 0 else -1
    big = 1.7976931348623157e308
    tx = (vx + (1 if sx > 0 else 0) - ox) / dx if dx != 0 else big
    ty = (vy + (1 if sy > 0 else 0) - oy) / dy if dy != 0 else big
    tz = (vz + (1 if sz > 0 else 0) - oz) / dz if dz != 0 else big
    ddx = sx / dx if dx != 0 else big
    ddy = sy / dy if dy != 0 else big
    ddz = sz / dz if dz != 0 else big
    if not (0 <= vx < X and 0 <= vy < Y and 0 <= vz < Z):
        return _cast_from_outside(labels, free_label, vx, vy, vz, sx, sy, sz, tx, ty, tz, ddx, ddy, ddz)
    # Hot loop: the voxel is inside; only the axis just stepped can leave the grid.
    while True:
        lab = labels[vx, vy, vz]
        # exit distance of this voxel; ties go y before x and z before both (as the reference)
        if tx < ty:
            axis = 0 if tx < tz else 2
        else:
            axis = 1 if ty < tz else 2
        if axis == 0:
            t = tx
        elif axis == 1:
            t = ty
        else:
            t = tz
        if lab != free_label:
            return t, int(lab), (vx * Y + vy) * Z + vz
        if axis == 0:
            vx += sx
            tx += ddx
            if vx < 0 or vx >= X:
                break
        elif axis == 1:
            vy += sy
            ty += ddy
            if vy < 0 or vy >= Y:
                break
        else:
            vz += sz
            tz += ddz
            if vz < 0 or vz >= Z:
                break
    return np.nan, free_label, -1


@njit(cache=True)
def _cast_from_outside(labels: np.ndarray, free_label: int, vx: int, vy: int, vz: int, sx: int, sy: int,
                       sz: int, tx: float, ty: float, tz: float, ddx: float, ddy: float,
                       ddz: float) -> tuple[float, int, int]:
    """`_cast_one` for an origin outside the grid: step (at most the reference's 1000 steps) until the
    ray enters, then as usual until it leaves."""
    X, Y, Z = labels.shape
    was_inside = False
    for _ in range(_MAX_STEPS + 1):
        inside = 0 <= vx < X and 0 <= vy < Y and 0 <= vz < Z
        lab = free_label
        here = -1
        if inside:
            was_inside = True
            lab = int(labels[vx, vy, vz])
            here = (vx * Y + vy) * Z + vz
        elif was_inside:
            break
        if tx < ty:
            if tx < tz:
                t = tx
                vx += sx
                tx += ddx
            else:
                t = tz
                vz += sz
                tz += ddz
        elif ty < tz:
            t = ty
            vy += sy
            ty += ddy
        else:
            t = tz
            vz += sz
            tz += ddz
        if lab != free_label:
            return t, lab, here
    return np.nan, free_label, -1


@njit(cache=True, parallel=True)
def _first_hits_kernel(labels: np.ndarray, origins_v: np.ndarray, ends_v: np.ndarray, free_label: int,
                       dist_v: np.ndarray, cls: np.ndarray, index: np.ndarray) -> None:
    """Fill `dist_v (n, R) float32` (voxel units), `cls (n, R) uint8` and `index (n, R) int64` (the hit
    voxel's flat index, -1: none; what flow scoring reads) for every ray."""
    n, R = ends_v.shape[0], ends_v.shape[1]
    for q in prange(n * R):
        o = q // R
        r = q - o * R
        d, c, k = _cast_one(labels, free_label, np.float64(origins_v[o, 0]), np.float64(origins_v[o, 1]),
                            np.float64(origins_v[o, 2]), np.float64(ends_v[o, r, 0]), np.float64(ends_v[o, r, 1]),
                            np.float64(ends_v[o, r, 2]))
        dist_v[o, r] = d
        cls[o, r] = c
        index[o, r] = k


@njit(cache=True, parallel=True)
def _pair_hits_kernel(gt: np.ndarray, pred: np.ndarray, origins_v: np.ndarray, ends_v: np.ndarray,
                      free_label: int, gt_dist_v: np.ndarray, gt_cls: np.ndarray, gt_index: np.ndarray,
                      pred_dist_v: np.ndarray, pred_cls: np.ndarray, pred_index: np.ndarray) -> None:
    """`_first_hits_kernel` through truth and prediction at once; a ray whose truth hits nothing is
    dropped by the metric, so its prediction is not cast (left as no hit)."""
    n, R = ends_v.shape[0], ends_v.shape[1]
    for q in prange(n * R):
        o = q // R
        r = q - o * R
        ox, oy, oz = np.float64(origins_v[o, 0]), np.float64(origins_v[o, 1]), np.float64(origins_v[o, 2])
        ex, ey, ez = np.float64(ends_v[o, r, 0]), np.float64(ends_v[o, r, 1]), np.float64(ends_v[o, r, 2])
        d, c, k = _cast_one(gt, free_label, ox, oy, oz, ex, ey, ez)
        gt_dist_v[o, r] = d
        gt_cls[o, r] = c
        gt_index[o, r] = k
        if c != free_label:
            d, c, k = _cast_one(pred, free_label, ox, oy, oz, ex, ey, ez)
        else:
            d, c, k = np.nan, free_label, -1
        pred_dist_v[o, r] = d
        pred_cls[o, r] = c
        pred_index[o, r] = k


def _check_grid(labels: np.ndarray, grid: OccGrid, what: str) -> np.ndarray:
    a = _as_labels(labels, what)
    if a.shape != grid.shape:
        raise OccDataError(f"{what} shape {a.shape} does not match the grid {grid.shape}")
    return a


def _to_metres(dist_v: np.ndarray, grid: OccGrid) -> np.ndarray:
    # The reference stores the voxel-unit distance as float32, then multiplies by the voxel size in float32.
    return (dist_v.astype(np.float32) * np.float32(grid.voxel_size)).astype(np.float32)


def first_hits(labels: np.ndarray, origins_keyego: np.ndarray, directions: np.ndarray | None = None,
               grid: OccGrid = GRID, free_label: int = FREE_LABEL) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays through a label grid; numba 3D DDA (Amanatides & Woo).

    `labels (X, Y, Z) uint8` (occupied = label != free), `origins_keyego (n, 3)` metres,
    `directions (R, 3) float32` unit vectors (default: `lidar_ray_directions()`).
    Returns `dist (n, R) float32` metres from the origin to where the ray LEAVES the first occupied
    voxel (NaN: no hit before leaving the grid) and `cls (n, R) uint8`, that voxel's label
    (free_label: no hit)."""
    return first_hit_voxels(labels, origins_keyego, directions, grid, free_label)[:2]


def first_hit_voxels(labels: np.ndarray, origins_keyego: np.ndarray, directions: np.ndarray | None = None,
                     grid: OccGrid = GRID, free_label: int = FREE_LABEL) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`first_hits` plus each ray's first-hit voxel, a flat index `(n, R) int64` into `labels.ravel()`
    (-1: no hit; what flow scoring reads there); numba. Its numpy twin: tests/reference/."""
    lab = _check_grid(labels, grid, "labels")
    dirs = _rays() if directions is None else np.asarray(directions, np.float32).reshape(-1, 3)
    o_v, e_v = _ray_setup(origins_keyego, dirs, grid)
    shape = e_v.shape[:2]
    dist_v, cls, index = np.empty(shape, np.float32), np.empty(shape, np.uint8), np.empty(shape, np.int64)
    if dist_v.size:
        _first_hits_kernel(lab, o_v, e_v, free_label, dist_v, cls, index)
    return _to_metres(dist_v, grid), cls, index


def ray_counts(gt_dist: np.ndarray, gt_cls: np.ndarray, pred_dist: np.ndarray, pred_cls: np.ndarray,
               taus: Sequence[float] = RAYIOU_TAUS, num_classes: int = NUM_CLASSES,
               free_label: int = FREE_LABEL) -> np.ndarray:
    """Per-class ray counts of one sample, `(2 + T, K) int64`: truth rays, predicted rays, then
    true positives per tau. Rays whose truth hits nothing are dropped; a TP has the same class and
    |d_pred - d_gt| < tau (float32, strict)."""
    valid = np.asarray(gt_cls).ravel() != free_label
    gc = np.asarray(gt_cls).ravel()[valid].astype(np.int64)
    pc = np.asarray(pred_cls).ravel()[valid].astype(np.int64)
    err = np.abs(np.asarray(pred_dist, np.float32).ravel()[valid] - np.asarray(gt_dist, np.float32).ravel()[valid])
    same = gc == pc
    out = np.zeros((2 + len(taus), num_classes), np.int64)
    out[0] = np.bincount(gc, minlength=num_classes)
    out[1] = np.bincount(pc, minlength=num_classes)
    for j, tau in enumerate(taus):
        out[2 + j] = np.bincount(gc[same & (err < np.float32(tau))], minlength=num_classes)
    return out


@dataclass(frozen=True)
class RayIoUResult:
    """RayIoU of a split. `per_class (T, K-1) float64` IoU per tau and non-free class (NaN: class
    never seen by a truth or predicted ray), `rayiou_at {tau: mean over classes}`, `rayiou` = mean
    over all T x (K-1) values (NaN skipped), `counts (2 + T, K) int64` as in `ray_counts`.

    With flow scored (`occdata.eval.flow.RayFlowAccumulator`; else None / NaN): `ave_per_class
    (K-1,) float64` m/s (NaN: not a moving class, or no true-positive ray of it), `mave` (NaN: no
    moving class has one), `occ_score` = 0.9 `rayiou` + 0.1 max(1 - `mave`, 0) (NaN with `mave`)."""

    per_class: np.ndarray
    rayiou_at: dict[float, float]
    rayiou: float
    counts: np.ndarray
    ave_per_class: np.ndarray | None = None
    mave: float = float("nan")
    occ_score: float = float("nan")


class RayIoUAccumulator:
    """RayIoU (SparseOcc protocol) over a split: ray counts updated per sample, mergeable.

    >>> acc = RayIoUAccumulator()  # origins: occdata.eval.rays.scene_ray_origins(reader, i)
    >>> acc.update(gt, pred, origins); acc.result().rayiou
    """

    def __init__(self, taus: Sequence[float] = RAYIOU_TAUS, grid: OccGrid = GRID,
                 num_classes: int = NUM_CLASSES, free_label: int = FREE_LABEL) -> None:
        self.taus = tuple(float(t) for t in taus)
        self.grid = grid
        self.num_classes = num_classes
        self.free_label = free_label
        self._counts = np.zeros((2 + len(self.taus), num_classes), np.int64)
        self.n_samples = 0

    def update(self, gt: np.ndarray, pred: np.ndarray, origins_keyego: np.ndarray) -> None:
        """Add one sample: `gt`, `pred (X, Y, Z) uint8` labels, `origins_keyego (n, 3)` metres."""
        gd, gc, _, pd, pc, _ = self._pair_hits(gt, pred, origins_keyego)
        self._counts += ray_counts(gd, gc, pd, pc, self.taus, self.num_classes, self.free_label)
        self.n_samples += 1

    def _pair_hits(self, gt: np.ndarray, pred: np.ndarray, origins_keyego: np.ndarray) -> tuple[np.ndarray, ...]:
        """Both grids checked, every ray cast through both: `(gt_dist, gt_cls, gt_index, pred_dist, pred_cls,
        pred_index)`, each `(n, R)`; distances in metres, indices flat into the grid (-1: no hit)."""
        g = _check_grid(gt, self.grid, "ground truth")
        p = _check_grid(pred, self.grid, "prediction")
        if int(p.max()) >= self.num_classes:
            raise OccDataError(f"prediction has labels >= {self.num_classes} (max {int(p.max())}); "
                               f"labels must be 0..{self.num_classes - 1}")
        if int(g.max()) >= self.num_classes:
            raise OccDataError(f"ground truth has labels >= {self.num_classes} (max {int(g.max())}); "
                               "is the sample labelled?")
        o_v, e_v = _ray_setup(origins_keyego, _rays(), self.grid)
        shape = e_v.shape[:2]
        gd, pd = np.empty(shape, np.float32), np.empty(shape, np.float32)
        gc, pc = np.empty(shape, np.uint8), np.empty(shape, np.uint8)
        gi, pi = np.empty(shape, np.int64), np.empty(shape, np.int64)
        if gd.size:
            _pair_hits_kernel(g, p, o_v, e_v, self.free_label, gd, gc, gi, pd, pc, pi)
        return _to_metres(gd, self.grid), gc, gi, _to_metres(pd, self.grid), pc, pi

    @property
    def state(self) -> np.ndarray:
        """Counts `(2 + T, K) int64` (a copy): truth rays, predicted rays, TPs per tau."""
        return self._counts.copy()

    @classmethod
    def from_state(cls, state: np.ndarray, taus: Sequence[float] = RAYIOU_TAUS) -> RayIoUAccumulator:
        state = np.asarray(state)
        if state.ndim != 2 or state.shape[0] != 2 + len(taus):
            raise OccDataError(f"RayIoU state for {len(taus)} taus must be ({2 + len(taus)}, K), got {state.shape}")
        acc = cls(taus, num_classes=state.shape[1])
        acc._counts = state.astype(np.int64, copy=True)
        return acc

    def merge(self, other: RayIoUAccumulator) -> RayIoUAccumulator:
        """Add another accumulator's counts into this one (returns self)."""
        if other.taus != self.taus or other._counts.shape != self._counts.shape:
            raise OccDataError("cannot merge RayIoU accumulators with different taus or class counts")
        self._counts += other._counts
        self.n_samples += other.n_samples
        return self

    def result(self) -> RayIoUResult:
        c = self._counts
        gt, pred, tp = c[0], c[1], c[2:]
        iou = _ratio(tp, gt[None] + pred[None] - tp)
        sem = [k for k in range(self.num_classes) if k != self.free_label]
        per = iou[:, sem]
        return RayIoUResult(per_class=per, rayiou_at={t: _nanmean(per[j]) for j, t in enumerate(self.taus)},
                            rayiou=_nanmean(per), counts=c.copy())
