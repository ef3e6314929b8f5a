"""Classes from the user's own 2D masks (`occdata labels --image-masks DIR`): each LiDAR point takes the
class of the pixel it projects to, where it is the surface that camera sees.

For a LiDAR frame taken at `t` and each camera channel, the image of that channel nearest in time to
`t` is used (cameras fire at keyframes; a sweep between two keyframes takes the nearer one). A point is
carried to the camera's time first: a static point stays where it is in the global frame (the ego
poses place the camera), a point in a box goes with its box (the box at the camera's time). It then
**votes** in a camera when it projects into the image, in front of it, onto a pixel whose id maps to an
Occ3D class, and it is the visible surface there: the frame's points, carried alike, are projected
into that camera as a depth buffer of `cell` x `cell` pixel cells (the nearest depth per cell), and a
point whose depth exceeds the nearest depth of the `(2 radius + 1)^2` cells around its own by more
than `tolerance + tolerance_rel * nearest` m is hidden (a point behind a wall, or on the ground behind
a car that the roof LiDAR sees over and the camera does not). `cell` is the angle `cell_deg` in pixels
of that camera (a LiDAR ring is about 1.3 degrees apart). Where several cameras see a point, the one
nearest in time to its frame decides. A point with no vote keeps the class geometry gives it, and a
voxel takes the majority of its points' votes, the geometric classes only where it has none
(`occdata.labels.flat.tiered_majority`).

Every numba kernel here has a plain numpy twin in tests/reference/labels_paint.py and a test that they
agree.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit

from occdata.formats.imagemasks import IGNORE, MaskClasses, mask_path, read_mask
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.kernels import NO_LABEL
from occdata.nuscenes import CameraRecord, NuScenesDataset
from occdata.nuscenes.annotations import BoxRecord

__all__ = ["ImageMasks", "Painter", "depth_buffer", "paint_camera", "visible_points"]

_NEAR = 0.5  # m: points closer to a camera than this are not painted (behind or at the lens)


@dataclass(frozen=True, eq=False)
class ImageMasks:
    """`--image-masks DIR` (`root`) and its id mapping (`classes`), with the occlusion test's settings
    (module docstring): `cell_deg` (deg), `radius` (cells), `tolerance` (m), `tolerance_rel`."""

    root: Path
    classes: MaskClasses = field(default_factory=MaskClasses.occ3d)
    cell_deg: float = 0.4
    radius: int = 1
    tolerance: float = 0.3
    tolerance_rel: float = 0.05

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        if not 0.01 <= self.cell_deg <= 5 or not 0 <= self.radius <= 5:
            raise ValueError("image masks: cell_deg must be in [0.01, 5] and radius in [0, 5]")
        if not 0 <= self.tolerance <= 10 or not 0 <= self.tolerance_rel <= 1:
            raise ValueError("image masks: tolerance must be in [0, 10] m and tolerance_rel in [0, 1]")

    def describe(self) -> dict[str, object]:
        """What labels.json records."""
        return {"root": str(self.root), "classes": self.classes.source, "cell_deg": self.cell_deg,
                "radius": self.radius, "tolerance": self.tolerance, "tolerance_rel": self.tolerance_rel}


@njit(cache=True)
def depth_buffer(cell_u: np.ndarray, cell_v: np.ndarray, depth: np.ndarray, n_u: int, n_v: int) -> np.ndarray:
    """`(n_v, n_u) float64`: per cell the least `depth (N,)` of the points in it (cells `cell_u`, `cell_v`
    `(N,) int64`, inside the buffer), `inf` where none."""
    out = np.full((n_v, n_u), np.inf)
    for n in range(depth.shape[0]):
        if depth[n] < out[cell_v[n], cell_u[n]]:
            out[cell_v[n], cell_u[n]] = depth[n]
    return out


@njit(cache=True)
def visible_points(cell_u: np.ndarray, cell_v: np.ndarray, depth: np.ndarray, buffer: np.ndarray, radius: int,
                   tolerance: float, tolerance_rel: float) -> np.ndarray:
    """`(N,) bool`: the points (cells `cell_u`, `cell_v` `(N,) int64`, `depth (N,) float64`) no deeper than
    `nearest + tolerance + tolerance_rel * nearest`, `nearest` the least of `buffer (V, U)`
    (`depth_buffer`) over the cells within `radius` of the point's (in each axis)."""
    n_v, n_u = buffer.shape
    out = np.zeros(depth.shape[0], np.bool_)
    for n in range(depth.shape[0]):
        nearest = np.inf
        for v in range(max(cell_v[n] - radius, 0), min(cell_v[n] + radius + 1, n_v)):
            for u in range(max(cell_u[n] - radius, 0), min(cell_u[n] + radius + 1, n_u)):
                nearest = min(nearest, buffer[v, u])
        out[n] = depth[n] <= nearest + tolerance + tolerance_rel * nearest
    return out


def paint_camera(points_cam: np.ndarray, K: np.ndarray, mask: np.ndarray, opts: ImageMasks) -> np.ndarray:
    """`(N,) uint8`: the class of the pixel of `mask (H, W) uint8` (Occ3D classes, `IGNORE`) each of
    `points_cam (N, 3) float64` (camera frame, z forward) projects to through `K (3, 3)`, where it is
    the visible surface (module docstring); `NO_LABEL` elsewhere."""
    height, width = mask.shape
    out = np.full(len(points_cam), NO_LABEL, np.uint8)
    z = points_cam[:, 2]
    front = np.flatnonzero(z > _NEAR)
    uvw = points_cam[front] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    col, row = np.floor(uv[:, 0] + 0.5).astype(np.int64), np.floor(uv[:, 1] + 0.5).astype(np.int64)
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    front, col, row = front[inside], col[inside], row[inside]
    if not len(front):
        return out
    cell = max(1, int(round(float(K[0, 0]) * np.tan(np.deg2rad(opts.cell_deg)))))
    cu, cv = col // cell, row // cell
    depth = np.ascontiguousarray(z[front])
    buffer = depth_buffer(cu, cv, depth, -(-width // cell), -(-height // cell))
    seen = visible_points(cu, cv, depth, buffer, opts.radius, opts.tolerance, opts.tolerance_rel)
    cls = mask[row, col]
    vote = seen & (cls != IGNORE)
    out[front[vote]] = cls[vote]
    return out


class Painter:
    """Paints one scene's LiDAR frames from its cameras' masks (module docstring). `dataset`: the
    scene's slice; `boxes_at(sample_index, t_us)`: the boxes at a time (None: the scene has none, or
    they are withheld: every point is carried as static). Masks are read on first use and the most
    recent `cache` images kept."""

    def __init__(self, dataset: NuScenesDataset, opts: ImageMasks,
                 boxes_at: Callable[[int, int], tuple[BoxRecord, ...]] | None = None, cache: int = 48) -> None:
        self.opts = opts
        self.root = Path(dataset.root)
        self.samples = dataset.samples
        self.boxes_at = boxes_at
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()
        self._size = cache
        self._boxes: dict[tuple[int, int], dict[str, BoxRecord]] = {}  # (sample, camera time) -> instance -> box
        self.channels = sorted({c.channel for s in self.samples for c in s.cameras})

    def _mask(self, cam: CameraRecord) -> np.ndarray:
        key = str(cam.path)
        if key not in self._cache:
            try:
                rel = cam.path.relative_to(self.root)
            except ValueError:
                rel = Path(cam.path.name)
            self._cache[key] = read_mask(mask_path(self.opts.root, rel), cam.width, cam.height, self.opts.classes)
            if len(self._cache) > self._size:
                self._cache.popitem(last=False)
        self._cache.move_to_end(key)
        return self._cache[key]

    def _nearest(self, t_us: int) -> list[tuple[int, CameraRecord]]:
        """Per camera channel, (sample index, camera) of the image nearest in time to `t_us`, the
        farthest in time first (so that the nearest camera's vote is written last and wins)."""
        best: dict[str, tuple[int, int, CameraRecord]] = {}
        for i, s in enumerate(self.samples):
            for cam in s.cameras:
                dt = abs(cam.timestamp - t_us)
                if cam.channel not in best or dt < best[cam.channel][0]:
                    best[cam.channel] = (dt, i, cam)
        return [(i, cam) for _, i, cam in sorted(best.values(), key=lambda x: -x[0])]

    def paint(self, points: np.ndarray, t_us: int, boxes: tuple[BoxRecord, ...] = (),
              box_index: np.ndarray | None = None) -> np.ndarray:
        """`(N,) uint8`: the painted class of each of a frame's `points (N, 3) float64` (global, taken at
        `t_us`), `NO_LABEL` where no camera gave it one. `box_index (N,) int`: the index in `boxes`
        (the frame's) of each point's box, -1 none: those points move with their box."""
        out = np.full(len(points), NO_LABEL, np.uint8)
        for i, cam in self._nearest(t_us):
            moved = self._carried(points, boxes, box_index, i, cam.timestamp)
            T_cam_from_global = invert_rigid(cam.T_global_from_ego @ cam.T_ego_from_cam)
            cls = paint_camera(transform_points(T_cam_from_global, moved), cam.K, self._mask(cam), self.opts)
            out = np.where(cls != NO_LABEL, cls, out)
        return out

    def _carried(self, points: np.ndarray, boxes: tuple[BoxRecord, ...], box_index: np.ndarray | None,
                 sample_index: int, t_cam: int) -> np.ndarray:
        """`points (N, 3)` at the camera's time `t_cam`: each one in a box moved with its instance's box
        there (an instance with no box then stays)."""
        if box_index is None or self.boxes_at is None or not boxes or not (box_index >= 0).any():
            return points
        key = (sample_index, t_cam)  # one camera serves every frame nearest to it: interpolate once
        if key not in self._boxes:
            self._boxes[key] = {b.instance_token: b for b in self.boxes_at(sample_index, t_cam)}
        later = self._boxes[key]
        out = np.array(points, np.float64)
        for b in np.unique(box_index[box_index >= 0]):
            then = later.get(boxes[b].instance_token)
            if then is not None:
                sel = box_index == b
                T = then.T_global_from_box() @ invert_rigid(boxes[b].T_global_from_box())
                out[sel] = transform_points(T, points[sel])
        return out
