"""Ground from geometry, and the two-tier vote that image masks need.

Without lidarseg and without masks every static point used to be one class (`others`). The scene's
ground model (`occdata.labels.heights`, as carving fits it: per column the lowest surface any keyframe
slot saw, each slot's heights aligned first) splits off the ground: a static point within `clearance`
m of its column's ground (after its own slot's height error is taken off) is **flat** and takes
`flat_class` (one of Occ3D's 11-14 as a stand-in: the geometry cannot tell road from sidewalk or
grass); the other static points keep `static_class`. For labels the model reaches as far as the
LiDAR (`REACH`; carving keeps to 30 m) and keeps columns with a single point near their lowest, and
where a 0.5 m column has no ground seen the 2 m column around it gives it (`SceneGround`): far off,
a LiDAR's rings are metres apart. A column whose lowest surface stands more than `STEP` m over the
lowest one within 3 m (2 m columns, the 3 x 3 around its own) saw no ground but a roof, a car or the
upper part of a wall: it has none. Points of columns whose ground no slot saw stay static.

The bottom voxel of a wall, a pole, a trunk or a car holds its foot within `clearance` of the ground,
and the ground beside it: geometry alone (and a mask, whose road runs under the car's edge) would call
it flat. So after the vote a flat voxel is **covered** (`uncover`) when the `COVER` voxels above it are
occupied by something not flat (one voxel of `others` on the ground is more likely its own noise): it
takes the most voted class of its other points, or, with none, the class of the voxel above (what
stands on it reaches down to the ground, as Occ3D's voxels of an object touch it). Overhangs lower
than one voxel over the ground are rare; a tree's crown higher than that does not cover the grass.

With image masks a point's class is either painted (tier 1: the masks, and a box's class) or
geometric (tier 2: flat / static / dynamic, where no mask voted). Classes travel in one `uint8` as
`c` (tier 1) or `n + c` (tier 2), `n` = 17 semantic classes; `tiered_majority` gives each voxel the
majority of its tier-1 votes, and the majority of its tier-2 votes where it has none. A voxel that
geometry alone called flat then takes the most common flat class (Occ3D's 11-14) of the voxels around
it that masks decided (`fill_flat`: within `FILL` voxels across, one up or down), when there are any:
far off or at a grazing angle the occlusion test rejects most ground points, and the road, sidewalk
or grass there is the one the masks saw next to it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from occdata.labels.heights import COLUMN_M, GroundMap, HeightOffsets, ground_cells
from occdata.labels.kernels import majority

__all__ = ["FLAT_CLASS", "FLAT_CLEARANCE", "SceneGround", "fill_flat", "fold_votes", "on_ground", "tiered_majority",
           "uncover"]

FLAT_CLASS = 11  # driveable_surface: the default stand-in for "the scene's ground"
FLAT_CLEARANCE = 0.2  # m over the column's ground within which a static point is flat
REACH = 80.0  # m from a slot's LiDAR within which its lowest surfaces count (the synthetic LiDAR's range)
COARSE_M = 2.0  # m: the column that stands in where a 0.5 m column saw no ground
FILL = 2  # voxels across within which `fill_flat` looks for a flat class the masks gave
COVER = 2  # voxels: how tall what stands on a flat voxel must be to cover it (a 1-voxel lump is ground noise)
STEP = 0.5  # m: the most a column's ground may stand over the lowest around it (kerbs, slopes)


@dataclass(frozen=True, eq=False)
class SceneGround:
    """A scene's ground for labels: the slots' height errors `heights`, and the lowest surface per 0.5 m
    column (`fine`) and per 2 m column (`coarse`), in aligned heights."""

    heights: HeightOffsets
    fine: GroundMap
    coarse: GroundMap

    @classmethod
    def fit(cls, slots: Sequence[tuple[np.ndarray, np.ndarray, int]], heights: HeightOffsets) -> SceneGround:
        """From each keyframe slot's `(origin (3,), points (N, 3), t_us)` (global, off the ego) and the
        slots' height errors (`occdata.labels.heights.height_offsets`)."""
        dz = np.array([heights.at(t) for _, _, t in slots])
        maps = [_median_map([ground_cells(p, o, cell, REACH, min_points=1) for o, p, _ in slots], dz, cell)
                for cell in (COLUMN_M, COARSE_M)]
        return cls(heights, *maps)

    def height_under(self, points: np.ndarray) -> np.ndarray:
        """`(N,) float64`: the ground height under each of `points (N, 3)` (aligned), NaN where unseen
        (module docstring: the 0.5 m column's, else the 2 m column's, if not `STEP` over the lowest around)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        z = self.fine.height_under(points)
        gap = np.isnan(z)
        z[gap] = self.coarse.height_under(points[gap])
        lowest = np.full(len(points), np.inf)
        for dx in (-COARSE_M, 0.0, COARSE_M):
            for dy in (-COARSE_M, 0.0, COARSE_M):
                around = self.coarse.height_under(points + [dx, dy, 0.0])
                lowest = np.fmin(lowest, around)
        z[z > lowest + STEP] = np.nan
        return z


def _median_map(cells: Sequence[tuple[np.ndarray, np.ndarray]], dz: np.ndarray, cell: float) -> GroundMap:
    """Per column, the median over the slots that saw its ground of their lowest surface there, each less
    its slot's height error (the lower middle one of an even count). Carving's map takes the lowest
    (`occdata.labels.heights.ground_map`): for labels one badly aligned slot must not sink a column's
    ground under the road that every other slot saw (real scene-0916: 0.4 m under it near the ego)."""
    keys = np.concatenate([k for k, _ in cells]) if cells else np.zeros(0, np.int64)
    z = np.concatenate([h - d for (_, h), d in zip(cells, dz, strict=True)]) if cells else np.zeros(0)
    order = np.lexsort((z, keys))
    keys, z = keys[order], z[order]
    first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if len(keys) else np.zeros(0, np.int64)
    size = np.diff(np.r_[first, len(keys)])
    middle = first + (size - 1) // 2
    return GroundMap(keys[first], z[middle], cell)


def on_ground(points: np.ndarray, t_us: int, ground: SceneGround, clearance: float) -> np.ndarray:
    """`(N,) bool`: which of a frame's `points (N, 3) float64` (global, taken at `t_us`) lie within
    `clearance` m over the ground of their column, heights aligned (`ground.heights.at(t_us)` taken
    off); False where no slot saw that column's ground."""
    pts = np.array(points, np.float64).reshape(-1, 3)
    pts[:, 2] -= ground.heights.at(t_us)
    above = pts[:, 2] - ground.height_under(pts)
    return np.nan_to_num(above, nan=np.inf) <= clearance


def fold_votes(votes: list[np.ndarray], n: int) -> list[np.ndarray]:
    """Two-tier vote keys (`voxel * 2n + c`, `c < 2n`) as plain ones (`voxel * n + c mod n`)."""
    return [(k // (2 * n)) * n + (k % (2 * n)) % n for k in votes]


def tiered_majority(votes: list[np.ndarray], shape: tuple[int, int, int], n: int,
                    empty: int) -> tuple[np.ndarray, np.ndarray]:
    """`(X, Y, Z) uint8` semantics from two-tier vote keys (`vote_voxels` with `2n` classes): per voxel
    the most voted tier-1 class (`c < n`), else the most voted tier-2 class (`c - n`), ties to the lower
    class; `empty` without votes. And `(X, Y, Z) bool`: the voxels that tier 2 decided."""
    keys = np.concatenate([np.zeros(0, np.int64), *votes])
    tier1 = (keys % (2 * n)) < n
    none = 255  # not `empty`: tier-2 class n + c may equal it
    first = majority([keys[tier1]], shape, 2 * n, none)
    second = majority([keys[~tier1]], shape, 2 * n, none)
    by_geometry = (first == none) & (second != none)
    out = np.where(first != none, first, np.where(by_geometry, second.astype(np.int64) - n, empty))
    return out.astype(np.uint8), by_geometry


def fill_flat(semantics: np.ndarray, by_geometry: np.ndarray, flat_class: int,
              flat_classes: tuple[int, ...] = (11, 12, 13, 14), radius: int = FILL) -> np.ndarray:
    """`semantics (X, Y, Z) uint8` with each voxel of `by_geometry (X, Y, Z) bool` (tier 2) that holds
    `flat_class` given the most common of `flat_classes` among the other voxels within `radius` in x
    and y and 1 in z (ties to the lower class); unchanged where there is none."""
    target = by_geometry & (semantics == flat_class)
    if not target.any():
        return semantics
    painted = ~by_geometry
    counts = np.zeros((len(flat_classes), *semantics.shape), np.float32)
    size = (2 * radius + 1, 2 * radius + 1)
    for c, cls in enumerate(flat_classes):
        layer = (painted & (semantics == cls)).astype(np.float32)
        across = np.stack([cv2.boxFilter(layer[:, :, z], -1, size, normalize=False,
                                         borderType=cv2.BORDER_CONSTANT) for z in range(layer.shape[2])], 2)
        counts[c] = across
        counts[c, :, :, 1:] += across[:, :, :-1]
        counts[c, :, :, :-1] += across[:, :, 1:]
    best = np.argmax(counts, axis=0)
    found = counts.max(axis=0) > 0
    out = semantics.copy()
    fill = target & found
    out[fill] = np.asarray(flat_classes, np.uint8)[best[fill]]
    return out


def uncover(semantics: np.ndarray, votes: list[np.ndarray], n: int, flat_class: int, empty: int,
            region: np.ndarray | None = None) -> np.ndarray:
    """`semantics (X, Y, Z) uint8` (z up) with each covered flat voxel (module docstring; within
    `region (X, Y, Z) bool` when given) given the most voted class of its other votes (`votes`: plain
    `vote_voxels` keys, `n` classes), the class of the voxel above without any. A stack of flat voxels
    under something is uncovered from the top down (one pass per voxel of the stack)."""
    keys = np.concatenate([np.zeros(0, np.int64), *votes])
    out = semantics
    for _ in range(semantics.shape[2]):
        standing = (out != empty) & (out != flat_class)
        above = np.zeros(out.shape, bool)  # something at least COVER voxels tall stands on the voxel
        above[:, :, :-COVER] = np.logical_and.reduce([standing[:, :, d:out.shape[2] - COVER + d]
                                                      for d in range(1, COVER + 1)])
        covered = (out == flat_class) & above
        if region is not None:
            covered &= region
        if not covered.any():
            break
        keep = covered.reshape(-1)[keys // n] & (keys % n != flat_class)
        other = majority([keys[keep]], out.shape, n, empty)
        up = np.full(out.shape, empty, np.uint8)
        up[:, :, :-1] = out[:, :, 1:]
        out = out.copy()
        out[covered] = np.where(other[covered] == empty, up[covered], other[covered])
    return out
