"""How close generated labels are to a known truth (the synthetic world's exact labels).

Pure functions over `(X, Y, Z) uint8` grids (17 = free): precision of the generated occupied voxels,
recall of the truth's observable surface (and of its camera-visible part, and of every camera-visible
occupied voxel, what `occdata eval` scores), semantic agreement, each also per band of distance from
the ego (`BANDS`), and for moving objects the share of an instance's generated voxels that lie in its
box at that keyframe. Used by the tests and by
`benchmarks/bench_labels.py`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occdata.constants import FREE_LABEL, GRID, OccGrid
from occdata.geometry import invert_rigid, points_in_box
from occdata.nuscenes.annotations import moving_instances

__all__ = ["BANDS", "Fidelity", "SceneScore", "band_regions", "instance_containment", "moving_containment",
           "observable_surface", "score_scene", "swept_path", "voxel_fidelity"]

# Bands of horizontal distance (m) from the key-ego origin to a voxel's centre: [lo, hi).
BANDS: tuple[tuple[float, float], ...] = ((0.0, 20.0), (20.0, 40.0), (40.0, np.inf))


@dataclass
class Fidelity:
    """Voxel counts summed over keyframes; the ratios are properties."""

    generated: int = 0  # occupied voxels generated
    true_positive: int = 0  # ... that are occupied in the truth
    surface: int = 0  # truth's observable surface voxels
    surface_found: int = 0  # ... generated occupied
    same_class: int = 0  # generated occupied, truly occupied, same class
    visible_surface: int = 0  # observable surface voxels in the truth's camera mask
    visible_surface_found: int = 0  # ... generated occupied
    visible: int = 0  # truth-occupied voxels in the truth's camera mask (what `occdata eval` scores)
    visible_found: int = 0  # ... generated occupied

    def add(self, other: Fidelity) -> None:
        for k, v in vars(other).items():
            setattr(self, k, getattr(self, k) + v)

    @property
    def precision(self) -> float:
        return self.true_positive / max(self.generated, 1)

    @property
    def recall(self) -> float:
        return self.surface_found / max(self.surface, 1)

    @property
    def semantic_agreement(self) -> float:
        return self.same_class / max(self.true_positive, 1)

    @property
    def visible_surface_recall(self) -> float:
        return self.visible_surface_found / max(self.visible_surface, 1)

    @property
    def visible_recall(self) -> float:
        return self.visible_found / max(self.visible, 1)


def band_regions(shape: tuple[int, int, int] = GRID.shape, grid: OccGrid = GRID) -> list[np.ndarray]:
    """Per band of `BANDS`, `(X, Y, Z) bool`: the voxels of `grid` (a key-ego grid; default Occ3D's)
    whose centre's horizontal distance from the key-ego origin lies in the band."""
    centres = grid.voxel_centers()
    if centres.shape[:3] != tuple(shape):
        raise ValueError(f"bands are defined on the grid {grid.shape}, not {shape}")
    r = np.hypot(centres[..., 0], centres[..., 1])
    return [(r >= lo) & (r < hi) for lo, hi in BANDS]


def observable_surface(truth: np.ndarray, mask_lidar: np.ndarray) -> np.ndarray:
    """`(X, Y, Z) bool`: truth-occupied voxels in `mask_lidar` with a 6-neighbour that is free and
    also in `mask_lidar` (a LiDAR could have seen that face; the inside of a filled solid is not)."""
    occ = truth != FREE_LABEL
    seen = mask_lidar != 0
    open_free = ~occ & seen
    near = np.zeros_like(occ)
    for axis in range(3):
        for shift in (1, -1):
            rolled = np.roll(open_free, shift, axis=axis)
            edge = [slice(None)] * 3
            edge[axis] = 0 if shift == 1 else -1
            rolled[tuple(edge)] = False  # no wrap-around
            near |= rolled
    return occ & seen & near


def voxel_fidelity(generated: np.ndarray, truth: np.ndarray, truth_mask_lidar: np.ndarray,
                   truth_mask_camera: np.ndarray | None = None, region: np.ndarray | None = None) -> Fidelity:
    """Counts for one keyframe's generated semantics against the truth's semantics and LiDAR mask (and
    camera mask: without one the `visible` counts stay 0), within `region (X, Y, Z) bool` (None: all)."""
    region = np.ones(truth.shape, bool) if region is None else region
    gen_occ = (generated != FREE_LABEL) & region
    true_occ = truth != FREE_LABEL
    surface = observable_surface(truth, truth_mask_lidar) & region
    both = gen_occ & true_occ
    out = Fidelity(
        generated=int(gen_occ.sum()), true_positive=int(both.sum()), surface=int(surface.sum()),
        surface_found=int((surface & gen_occ).sum()), same_class=int((both & (generated == truth)).sum()),
    )
    if truth_mask_camera is not None:
        cam = truth_mask_camera != 0
        out.visible_surface = int((surface & cam).sum())
        out.visible_surface_found = int((surface & cam & gen_occ).sum())
        out.visible = int((true_occ & cam & region).sum())
        out.visible_found = int((true_occ & cam & gen_occ).sum())
    return out


def _in_box(centers: np.ndarray, T_keyego_from_box: np.ndarray, size_wlh: np.ndarray, dilate: int,
            voxel_size: float = GRID.voxel_size) -> np.ndarray:
    w, length, h = np.asarray(size_wlh, np.float64)
    half = np.array([length / 2, w / 2, h / 2]) + dilate * voxel_size
    return points_in_box(centers, invert_rigid(T_keyego_from_box), half)


def instance_containment(generated: np.ndarray, cls: int, track: list[tuple[np.ndarray, np.ndarray]], now: int,
                         others: list[tuple[np.ndarray, np.ndarray]] = (), dilate: int = 1,
                         grid: OccGrid = GRID) -> tuple[int, int]:
    """A moving instance's generated voxels at one keyframe: `(inside, total)`.

    Its voxels are those of its class `cls` within the corridor it sweeps over the scene: the union of
    all its boxes `track` (`(T_keyego_from_box (4, 4), size_wlh (3,))` per annotation, in this
    keyframe's key ego), each grown by `dilate` voxels. `inside` counts those within its box at this
    keyframe, `track[now]`, grown the same way. Voxels in the other instances' boxes at this
    keyframe (`others`, grown the same way) belong to them and are left out. A smeared object fills
    the corridor; a sharp one stays in its box. `generated` lies on `grid` (key ego; default Occ3D's)."""
    idx = np.argwhere(generated == cls)
    if not len(idx):
        return 0, 0
    v = grid.voxel_size
    centers = np.asarray(grid.lower, np.float64) + (idx + 0.5) * v
    corridor = np.zeros(len(idx), bool)
    for T, size in track:
        corridor |= _in_box(centers, T, size, dilate, v)
    for T, size in others:
        corridor &= ~_in_box(centers, T, size, dilate, v)
    inside = _in_box(centers, *track[now], dilate, v) & corridor
    return int(inside.sum()), int(corridor.sum())


@dataclass
class SceneScore:
    """A scene's fidelity counts and, per moving instance, (inside, total) voxels summed over keyframes."""

    voxels: Fidelity
    moving: dict[str, tuple[int, int]]
    bands: list[Fidelity] = field(default_factory=list)  # per band of `BANDS`

    def moving_fraction(self) -> float:
        """Share of all moving instances' generated voxels that lie in their box (pooled)."""
        inside = sum(v[0] for v in self.moving.values())
        return inside / max(sum(v[1] for v in self.moving.values()), 1)

    def worst_instance(self, min_voxels: int = 20) -> float:
        """The lowest per-instance share among instances with at least `min_voxels` voxels."""
        shares = [i / t for i, t in self.moving.values() if t >= min_voxels]
        return min(shares, default=1.0)


def moving_containment(generated: list[np.ndarray], T_keyego_from_global: list[np.ndarray],
                       boxes_by_keyframe: list[list], class_of: dict[str, int],
                       grid: OccGrid = GRID) -> dict[str, tuple[int, int]]:
    """Per moving instance, `(inside, total)` generated voxels summed over the keyframes
    (`instance_containment`); `generated[k] (X, Y, Z) uint8` on `grid`, the key-ego transform and the
    BoxRecords of keyframe k; `class_of`: instance -> its Occ3D class."""
    movers = moving_instances(boxes_by_keyframe)
    tracks: dict[str, list] = {}
    for boxes in boxes_by_keyframe:
        for b in boxes:
            tracks.setdefault(b.instance_token, []).append(b)
    out: dict[str, tuple[int, int]] = {}
    for k, gen in enumerate(generated):
        T = T_keyego_from_global[k]
        for b in boxes_by_keyframe[k]:
            if b.instance_token not in movers:
                continue
            track = [(T @ o.T_global_from_box(), o.size_wlh) for o in tracks[b.instance_token]]
            now = next(i for i, o in enumerate(tracks[b.instance_token]) if o.token == b.token)
            others = [(T @ o.T_global_from_box(), o.size_wlh) for o in boxes_by_keyframe[k] if o is not b]
            i, t = instance_containment(gen, class_of[b.instance_token], track, now, others, grid=grid)
            old = out.get(b.instance_token, (0, 0))
            out[b.instance_token] = (old[0] + i, old[1] + t)
    return out


def score_scene(generated: list[np.ndarray], truth: list[tuple[np.ndarray, ...]],
                T_keyego_from_global: list[np.ndarray], boxes_by_keyframe: list[list],
                class_of: dict[str, int], grid: OccGrid = GRID) -> SceneScore:
    """Score one scene's keyframes: `generated[k]`, `truth[k] = (semantics, mask_lidar[, mask_camera])`
    and the arguments of `moving_containment`, on `grid` (a key-ego grid; default Occ3D's); also per
    band of `BANDS` when the arrays have `grid`'s shape."""
    total = Fidelity()
    regions = band_regions(grid.shape, grid) if generated and generated[0].shape == grid.shape else []
    bands = [Fidelity() for _ in regions]
    for gen, masks in zip(generated, truth, strict=True):
        if not regions:
            total.add(voxel_fidelity(gen, *masks))
        for band, region in zip(bands, regions, strict=True):
            band.add(voxel_fidelity(gen, *masks, region=region))
    for band in bands:  # the bands partition the grid and every count is per voxel: they sum to the whole
        total.add(band)
    moving = moving_containment(generated, T_keyego_from_global, boxes_by_keyframe, class_of, grid)
    return SceneScore(total, moving, bands)


def _box_voxels(T_keyego_from_box: np.ndarray, size_wlh: np.ndarray, dilate: int) -> np.ndarray:
    """`(X, Y, Z) bool` of Occ3D's grid: voxel centres in the box grown by `dilate` voxels (the
    box's bounding block alone is tested)."""
    w, length, h = np.asarray(size_wlh, np.float64)
    half = np.array([length / 2, w / 2, h / 2]) + dilate * GRID.voxel_size
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    c = corners @ T_keyego_from_box[:3, :3].T + T_keyego_from_box[:3, 3]
    lower, v, shape = np.asarray(GRID.lower), GRID.voxel_size, np.array(GRID.shape)
    i0 = np.clip(np.floor((c.min(axis=0) - lower) / v).astype(int), 0, shape)
    i1 = np.clip(np.ceil((c.max(axis=0) - lower) / v).astype(int) + 1, 0, shape)
    out = np.zeros(GRID.shape, bool)
    if (i1 <= i0).any():
        return out
    axes = [lower[a] + (np.arange(i0[a], i1[a]) + 0.5) * v for a in range(3)]
    block = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = points_in_box(block, invert_rigid(T_keyego_from_box), half)
    out[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]] = inside.reshape(i1 - i0)
    return out


def swept_path(generated: np.ndarray, reference_free: np.ndarray, T_keyego_from_global: np.ndarray,
               boxes_by_keyframe: list[list], now: int, movers: set[str], dilate: int = 1) -> tuple[int, int]:
    """Smear along moving objects' paths at keyframe `now`: `(wrong, free)` voxels.

    The path is the union of every box of the `movers` (instance tokens) over the scene's keyframes
    (`boxes_by_keyframe`, BoxRecords), moved into this keyframe's key ego, less every box at this
    keyframe (where something is now), each grown by `dilate` voxels. `free` counts the path's voxels
    free in the reference (`reference_free (X, Y, Z) bool`: the truth, or a box-aware run), `wrong`
    those of them occupied in `generated (X, Y, Z) uint8` (17 = free): what was left where an object
    passed. Occ3D's grid."""
    T = T_keyego_from_global
    path = np.zeros(GRID.shape, bool)
    for boxes in boxes_by_keyframe:
        for b in boxes:
            if b.instance_token in movers:
                path |= _box_voxels(T @ b.T_global_from_box(), b.size_wlh, dilate)
    for b in boxes_by_keyframe[now]:
        path &= ~_box_voxels(T @ b.T_global_from_box(), b.size_wlh, dilate)
    path &= reference_free
    return int((path & (generated != FREE_LABEL)).sum()), int(path.sum())
