"""What the viewer draws, as plain numpy (no viser, no torch): voxel layers, the error view, LiDAR points
lifted back to 3D, camera frustum parameters.

A label grid is drawn as LAYERS: one set of voxels per node id (a class, or an error kind and a class, or
"outside the mask"). Only the voxels of a layer that touch another layer (or the free space, or the grid
border) through one of their 6 faces are drawn: the inside of a block is never seen, and because the test
is per layer, hiding one layer never opens a hole into a hollow neighbour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occdata.constants import CLASS_COLORS, FREE_LABEL, GRID, OccGrid
from occdata.geometry import quaternion_wxyz_from_matrix

__all__ = [
    "EMPTY",
    "ERROR_COLORS",
    "ERROR_KINDS",
    "GHOST_COLOR",
    "N_SEMANTIC",
    "SPEED_BINS",
    "SPEED_COLORS",
    "STATIC_COLOR",
    "FrustumParams",
    "VoxelLayer",
    "error_ids",
    "exposed_voxels",
    "frustum_params",
    "label_ids",
    "layers_from_ids",
    "lift_depth_points",
    "speed_bin_name",
    "speed_ids",
]

N_SEMANTIC = FREE_LABEL  # 17 drawable classes, 0..16
EMPTY = -1  # node id of a voxel that is not drawn
ERROR_KINDS: tuple[str, ...] = ("right", "wrong", "missed")
# right: truth occupied, same class predicted; wrong: predicted occupied with another class than the
# truth (truth free included); missed: truth occupied, predicted free. Chosen away from the class colours.
ERROR_COLORS: tuple[tuple[int, int, int], ...] = ((40, 200, 90), (235, 40, 40), (40, 120, 255))
GHOST_COLOR = (150, 150, 150)  # occupied voxels outside the chosen mask
_GHOST_ID_LABEL = N_SEMANTIC  # 17
_GHOST_ID_ERROR = len(ERROR_KINDS) * N_SEMANTIC  # 51
# The speed view: occupied voxels coloured by |flow| (m/s) in bins [0.1, 1), [1, 2), ..., [9, inf); voxels
# slower than 0.1 m/s (static: buildings, road, parked cars) are one grey, darker than the mask's ghost grey.
SPEED_BINS: tuple[float, ...] = (0.1, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0)  # lower edges, m/s
SPEED_COLORS: tuple[tuple[int, int, int], ...] = (  # slow (blue) -> fast (dark red), one per bin
    (48, 18, 59), (65, 69, 171), (70, 117, 237), (57, 162, 252), (27, 207, 212), (36, 236, 166),
    (97, 252, 108), (210, 233, 53), (254, 155, 45), (217, 56, 6))
STATIC_COLOR = (95, 95, 95)
_STATIC_ID = 0
_GHOST_ID_SPEED = len(SPEED_BINS) + 1  # 11
SIDE_SHADE = 0.78  # colour factor of voxels whose top face is hidden (the flat style's only shading)


@dataclass(frozen=True, eq=False)
class VoxelLayer:
    """One drawable set of voxels.

    `name`: scene-node name below its group (e.g. `car`, `wrong/car`, `outside_mask`);
    `centers_ego (N, 3) float32` voxel centres in key ego (m); `top_exposed (N,) bool` whether each
    voxel's upper face is visible; `color` RGB; `class_id` the class whose toggle shows or hides the
    layer (None: no class, e.g. voxels outside the mask); `ghost` True for the outside-the-mask layer.
    """

    name: str
    centers_ego: np.ndarray
    top_exposed: np.ndarray
    color: tuple[int, int, int]
    class_id: int | None
    ghost: bool = False

    def colors(self, side_shade: float = SIDE_SHADE) -> np.ndarray:
        """`(N, 3) uint8`: the layer colour, darkened by `side_shade` where the top face is hidden."""
        base = np.asarray(self.color, dtype=np.float32)
        factor = np.where(self.top_exposed, 1.0, side_shade).astype(np.float32)
        return np.clip(np.rint(base[None, :] * factor[:, None]), 0, 255).astype(np.uint8)


def _occupied(labels: np.ndarray) -> np.ndarray:
    return np.asarray(labels) < N_SEMANTIC


def label_ids(labels: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Node ids `(X, Y, Z) int16` of a label or prediction grid `(X, Y, Z) uint8` (17 = free): the class
    (0..16) where occupied and inside `mask` (0/1, same shape; None = everything), 17 (outside the mask)
    where occupied and outside it, -1 where free."""
    lab = np.asarray(labels)
    occ = _occupied(lab)
    ids = np.where(occ, lab.astype(np.int16), np.int16(EMPTY))
    if mask is not None:
        ids[occ & (np.asarray(mask) == 0)] = _GHOST_ID_LABEL
    return ids


def error_ids(truth: np.ndarray, pred: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Node ids `(X, Y, Z) int16` of the error view: `kind * 17 + class` with kind 0 right, 1 wrong,
    2 missed (ERROR_KINDS); the class is the truth's where the truth is occupied, else the prediction's.
    Voxels outside `mask` that either grid occupies get 51; voxels free in both get -1. Inside the
    mask these are exactly the voxels that the Occ3D confusion matrix counts off its free/free cell."""
    gt, pr = np.asarray(truth), np.asarray(pred)
    gt_occ, pr_occ = _occupied(gt), _occupied(pr)
    cls = np.where(gt_occ, gt, pr).astype(np.int16)
    ids = np.full(gt.shape, EMPTY, dtype=np.int16)
    right = gt_occ & (pr == gt)
    wrong = pr_occ & (pr != gt)
    missed = gt_occ & ~pr_occ
    ids[right] = cls[right]
    ids[wrong] = N_SEMANTIC + cls[wrong]
    ids[missed] = 2 * N_SEMANTIC + cls[missed]
    if mask is not None:
        ids[(gt_occ | pr_occ) & (np.asarray(mask) == 0)] = _GHOST_ID_ERROR
    return ids


def speed_ids(labels: np.ndarray, flow: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Node ids `(X, Y, Z) int16` of the speed view: for occupied voxels of `labels (X, Y, Z) uint8`,
    0 where |flow| < 0.1 m/s (static), else 1 + the `SPEED_BINS` bin of |flow| (`flow (X, Y, Z, 2)`,
    (vx, vy) m/s); 11 where occupied and outside `mask`; -1 where free."""
    occ = _occupied(labels)
    f = np.asarray(flow, np.float32)
    speed = np.sqrt(f[..., 0] * f[..., 0] + f[..., 1] * f[..., 1])
    ids = np.where(occ, np.searchsorted(np.asarray(SPEED_BINS, np.float32), speed, side="right"),
                   EMPTY).astype(np.int16)  # 0 below the first edge, k past the k-th edge
    if mask is not None:
        ids[occ & (np.asarray(mask) == 0)] = _GHOST_ID_SPEED
    return ids


def speed_bin_name(k: int) -> str:
    """The legend's words for speed-view node id `k` (0 static, 1..10 a bin)."""
    if k == _STATIC_ID:
        return f"static (< {SPEED_BINS[0]:g} m/s)"
    lo = SPEED_BINS[k - 1]
    return f">= {lo:g} m/s" if k == len(SPEED_BINS) else f"{lo:g}-{SPEED_BINS[k]:g} m/s"


def exposed_voxels(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxels worth drawing in a node-id grid `(X, Y, Z) int` (-1 = nothing): those with at least one
    6-neighbour of another id (outside the grid counts as another id).

    Returns `ijk (N, 3) int64` (sorted by id, then x, y, z), `node (N,) int16` their ids and
    `top (N,) bool` whether the neighbour above has another id (the upper face is visible)."""
    ids = np.asarray(ids)
    pad = np.pad(ids, 1, mode="constant", constant_values=-2)
    core = pad[1:-1, 1:-1, 1:-1]
    top = pad[1:-1, 1:-1, 2:] != core
    show = top.copy()
    for axis in range(3):
        for lo in (0, 2):
            sl = [slice(1, -1)] * 3
            sl[axis] = slice(lo, lo + ids.shape[axis])
            show |= pad[tuple(sl)] != core
    show &= ids >= 0
    ijk = np.argwhere(show)
    node = ids[show].astype(np.int16)
    order = np.argsort(node, kind="stable")
    return ijk[order], node[order], top[show][order]


def _layer_meta(node: int, error_view: bool, speed_view: bool = False) -> tuple[str, tuple[int, int, int],
                                                                               int | None, bool]:
    """(name, colour, class, ghost) of a node id."""
    from occdata.constants import CLASS_NAMES

    if speed_view:
        if node == _GHOST_ID_SPEED:
            return "outside_mask", GHOST_COLOR, None, True
        if node == _STATIC_ID:
            return "static", STATIC_COLOR, None, False
        return f"speed_{node}", SPEED_COLORS[node - 1], None, False
    if error_view:
        if node == _GHOST_ID_ERROR:
            return "outside_mask", GHOST_COLOR, None, True
        kind, cls = divmod(node, N_SEMANTIC)
        return f"{ERROR_KINDS[kind]}/{CLASS_NAMES[cls]}", ERROR_COLORS[kind], cls, False
    if node == _GHOST_ID_LABEL:
        return "outside_mask", GHOST_COLOR, None, True
    return CLASS_NAMES[node], CLASS_COLORS[node], int(node), False


def layers_from_ids(ids: np.ndarray, error_view: bool = False, grid: OccGrid = GRID,
                    speed_view: bool = False) -> list[VoxelLayer]:
    """The drawable layers of a node-id grid (from `label_ids`, or `error_ids` with `error_view`, or
    `speed_ids` with `speed_view`: layers `static`, `speed_<k>` (k = 1..10) and `outside_mask`)."""
    ijk, node, top = exposed_voxels(ids)
    lower = np.asarray(grid.lower, dtype=np.float64)
    centers = (lower + grid.voxel_size * (ijk + 0.5)).astype(np.float32)
    values, starts = np.unique(node, return_index=True)
    ends = np.append(starts[1:], len(node))
    layers = []
    for value, a, b in zip(values.tolist(), starts.tolist(), ends.tolist(), strict=True):
        name, color, cls, ghost = _layer_meta(int(value), error_view, speed_view)
        layers.append(VoxelLayer(name=name, centers_ego=centers[a:b], top_exposed=top[a:b], color=color,
                                 class_id=cls, ghost=ghost))
    return layers


def lift_depth_points(uvd: np.ndarray, K: np.ndarray, T_keyego_from_cam: np.ndarray) -> np.ndarray:
    """Stored depth targets of one camera, `(M, 3)` (u, v in original-image pixels, depth = camera z, m),
    back to 3D: `(M, 3) float32` points in key ego (`p_cam = depth * inv(K) @ [u, v, 1]`)."""
    uvd = np.asarray(uvd, dtype=np.float64).reshape(-1, 3)
    K = np.asarray(K, dtype=np.float64)
    d = uvd[:, 2]
    x = (uvd[:, 0] - K[0, 2] - K[0, 1] * (uvd[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0] * d
    y = (uvd[:, 1] - K[1, 2]) / K[1, 1] * d
    points_cam = np.stack([x, y, d], axis=1)
    T = np.asarray(T_keyego_from_cam, dtype=np.float64)
    return (points_cam @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


@dataclass(frozen=True)
class FrustumParams:
    """A camera as the viewer draws it: `fov_y` vertical field of view (rad), `aspect` width / height,
    `wxyz` rotation and `position` (m) of the camera frame (x right, y down, z forward) in key ego."""

    fov_y: float
    aspect: float
    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]


def frustum_params(K: np.ndarray, image_size: tuple[int, int], T_keyego_from_cam: np.ndarray) -> FrustumParams:
    """Frustum of one camera from its intrinsics `K (3, 3)`, original `(width, height)` and pose `(4, 4)`."""
    w, h = (float(v) for v in image_size)
    fov_y = 2.0 * float(np.arctan2(h / 2.0, float(K[1, 1])))
    T = np.asarray(T_keyego_from_cam, dtype=np.float64)
    q = quaternion_wxyz_from_matrix(T[:3, :3])
    return FrustumParams(fov_y=fov_y, aspect=w / h, wxyz=tuple(float(v) for v in q),  # type: ignore[arg-type]
                         position=tuple(float(v) for v in T[:3, 3]))  # type: ignore[arg-type]
