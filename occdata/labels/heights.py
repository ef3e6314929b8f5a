"""Height alignment of a scene's LiDAR frames from the ground they share, for free-space carving.

nuScenes ego poses carry no height: every `ego_pose.translation` has z = 0, while the rotation keeps
the car's pitch and roll. On a road that climbs or dips, a frame therefore places the ground it sees
ahead at its true height *relative to itself*, and the frame taken there later places the same ground
at z = 0. On real scene-0916 the road dips 0.7 m, then climbs 1.6 m over 93 m, and keyframes 10-20 m
apart disagree by 0.33 m (median) about the height of the ground both saw: rays of one keyframe then pass through
the ground and walls that another keyframe's returns put a few decimetres higher, and carving takes
them for movers. Carving needs the frames consistent with each other, not with the world.

The model is one height error per time slot, `z_seen = z_true + dz[slot]`. Each slot's **ground
cells** are the lowest surface in each `cell` x `cell` m column of its points within `reach` m of its
LiDAR (the mean height of the points within `band` m of the column's lowest one; movers stand on the
ground, so the lowest surface of a column is ground wherever a frame saw it). Two slots that share at
least `min_common` such columns give one equation `dz[j] - dz[i] = median(z_j - z_i)` over them,
weighted by the square root of their count; the offsets are the weighted least-squares solution,
refitted once without the equations it fits worst (residual over 3 scaled MADs and 0.1 m), with a
small pull towards 0 (`ridge`) so that slots sharing no ground with the rest keep 0. On scene-0916 the
fit leaves 0.02 m (median) of the 0.33 m disagreement between keyframes 10-20 m apart; on the
synthetic worlds, whose poses are exact, the offsets stay within a few millimetres of 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["GroundMap", "HeightOffsets", "ground_cells", "ground_map", "height_offsets"]

COLUMN_M = 0.5  # the ground columns' side (m), for the slots' cells and the scene's map alike
_KEY = np.int64(1 << 31)  # column index packing: ix * _KEY + iy (|ix|, |iy| < 2^30 cells)


def _column_keys(points: np.ndarray, cell: float) -> np.ndarray:
    """`(N,) int64`: the packed key of the `cell`-m column of each of `points (N, 3) float64`."""
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    return ij[:, 0] * _KEY + ij[:, 1]


def _starts(keys: np.ndarray) -> np.ndarray:
    """`(G,) int64`: where each run of equal values of the sorted `keys (M,)` starts."""
    return np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if len(keys) else np.zeros(0, np.int64)


@dataclass(frozen=True, eq=False)
class HeightOffsets:
    """Height errors (m) of a scene's frames at times `times_us (S,) int64` (increasing), `dz (S,)
    float64`: a frame's points, less `at(its time)` in z, agree with the other frames'. Between and
    beyond the times the error is interpolated linearly / held (the sweeps between keyframes)."""

    times_us: np.ndarray
    dz: np.ndarray

    def __post_init__(self) -> None:
        if self.times_us.shape != self.dz.shape or self.times_us.ndim != 1 or len(self.times_us) == 0:
            raise ValueError("height offsets need one time per offset, at least one")
        if np.any(np.diff(self.times_us) <= 0) or not np.isfinite(self.dz).all():
            raise ValueError("height offsets need increasing times and finite offsets")

    @classmethod
    def zero(cls) -> HeightOffsets:
        return cls(np.zeros(1, np.int64), np.zeros(1))

    def at(self, t_us: int) -> float:
        return float(np.interp(float(t_us), self.times_us.astype(np.float64), self.dz))


@dataclass(frozen=True, eq=False)
class GroundMap:
    """The scene's ground: per `cell`-m column (sorted packed keys `keys (M,) int64`) the lowest surface
    any keyframe slot saw there, `z (M,) float64` in aligned heights (m)."""

    keys: np.ndarray
    z: np.ndarray
    cell: float

    def height_under(self, points: np.ndarray) -> np.ndarray:
        """`(N,) float64`: the ground height of the column of each of `points (N, 3)`; NaN where no slot
        saw that column's ground."""
        key = _column_keys(np.asarray(points, np.float64).reshape(-1, 3), self.cell)
        if not len(self.keys):
            return np.full(len(key), np.nan)
        at = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
        return np.where(self.keys[at] == key, self.z[at], np.nan)


def ground_map(cells: Sequence[tuple[np.ndarray, np.ndarray]], dz: np.ndarray, cell: float = COLUMN_M) -> GroundMap:
    """The lowest surface of each column over the slots' `ground_cells` `cells[s]`, each less its slot's
    height error `dz[s]`: where any slot saw the ground of a column, that is its ground (a mover hides
    the ground under it only while it is there)."""
    keys = np.concatenate([k for k, _ in cells]) if cells else np.zeros(0, np.int64)
    z = np.concatenate([h - d for (_, h), d in zip(cells, dz, strict=True)]) if cells else np.zeros(0)
    order = np.lexsort((z, keys))
    keys, z = keys[order], z[order]
    first = _starts(keys)
    return GroundMap(keys[first], z[first], cell)


def ground_cells(points: np.ndarray, origin: np.ndarray, cell: float = COLUMN_M, reach: float = 30.0,
                 band: float = 0.2, min_points: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The lowest surface of each `cell`-m column of `points (N, 3) float64` (global) within `reach` m
    (horizontally) of `origin (3,)`: `(keys (M,) int64` sorted column keys, `z (M,) float64)`, the mean
    height of the column's points within `band` m of its lowest; columns with fewer such points than
    `min_points` are left out."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.hypot(pts[:, 0] - origin[0], pts[:, 1] - origin[1]) <= reach]
    key = _column_keys(pts, cell)
    order = np.lexsort((pts[:, 2], key))
    key, z = key[order], pts[order, 2]
    if len(key) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    first = _starts(key)
    sizes = np.diff(np.r_[first, len(z)])
    near = z <= np.repeat(z[first], sizes) + band
    group = np.repeat(np.arange(len(first)), sizes)
    count = np.bincount(group, weights=near)
    total = np.bincount(group, weights=np.where(near, z, 0.0))
    keep = count >= min_points
    return key[first][keep], total[keep] / count[keep]


def height_offsets(cells: Sequence[tuple[np.ndarray, np.ndarray]], origins: np.ndarray, times_us: Sequence[int],
                   min_common: int = 20, reach: float = 30.0, ridge: float = 1e-3) -> HeightOffsets:
    """The slots' height errors (module docstring) from each slot's `ground_cells` `cells[s]`, its LiDAR
    origin `origins (S, 3)` (global; slots farther apart than 2 `reach` share no ground) and its time
    `times_us[s]` (increasing)."""
    n = len(cells)
    rows: list[tuple[int, int, float, float]] = []
    for i in range(n):
        for j in range(i + 1, n):
            if np.hypot(*(origins[j][:2] - origins[i][:2])) > 2 * reach:
                continue
            _, a, b = np.intersect1d(cells[i][0], cells[j][0], assume_unique=True, return_indices=True)
            if len(a) >= min_common:
                rows.append((i, j, float(np.median(cells[j][1][b] - cells[i][1][a])), float(np.sqrt(len(a)))))
    dz = _solve(rows, n, ridge)
    if rows:
        res = np.array([d - (dz[j] - dz[i]) for i, j, d, _ in rows])
        mad = 1.4826 * np.median(np.abs(res - np.median(res)))
        fit = np.abs(res) <= max(3 * mad, 0.1)
        dz = _solve([r for r, ok in zip(rows, fit, strict=True) if ok], n, ridge)
    return HeightOffsets(np.asarray(times_us, np.int64), dz)


def _solve(rows: list[tuple[int, int, float, float]], n: int, ridge: float) -> np.ndarray:
    """Weighted least squares of `dz[j] - dz[i] = d` (weight w) for rows `(i, j, d, w)`, plus `ridge * dz = 0`."""
    A = np.zeros((len(rows) + n, n))
    b = np.zeros(len(rows) + n)
    for r, (i, j, d, w) in enumerate(rows):
        A[r, i], A[r, j], b[r] = -w, w, w * d
    A[len(rows):] = ridge * np.eye(n)
    return np.linalg.lstsq(A, b, rcond=None)[0]
