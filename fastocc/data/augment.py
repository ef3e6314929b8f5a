"""Image and BEV augmentation as matrices (docs/design.md#augmentation).

Image: one 3x3 matrix A per camera maps an ORIGINAL-image pixel (u, v, 1) to the AUGMENTED input
pixel. Pixel coordinates follow OpenCV's convention (integer = pixel centre), so one
`cv2.warpAffine` with A (composed with the decode scale) is exactly "the point at u goes to A u".

BEV: one 4x4 matrix M maps key ego -> augmented key ego (x/y flips, optional rotation about z and
x/y scale); labels, masks and BEV GT are resampled into the augmented frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from occdata.constants import GRID

__all__ = [
    "BevAug",
    "BevAugConfig",
    "ImageAug",
    "ImageAugConfig",
    "T_decoded_from_original",
    "apply_bev_aug",
    "choose_reduce",
    "sample_bev_aug",
    "sample_image_aug",
]


@dataclass(frozen=True)
class ImageAugConfig:
    """Image augmentation ranges. `train=False` gives the deterministic test transform."""

    height: int = 256
    width: int = 704
    train: bool = True
    scale_jitter: tuple[float, float] = (-0.06, 0.11)  # added to s = width / original width
    rot_deg: float = 5.4  # rotation U(-rot_deg, rot_deg) about the crop centre
    flip_p: float = 0.5
    # Decode at 1/r (r in 1, 2, 4, 8; straight from the DCT) when that needs at most this much
    # upsampling afterwards: 1.1 keeps 256x704 at r = 2 for the whole scale range.
    max_upsample: float = 1.1


@dataclass(frozen=True)
class ImageAug:
    """One camera's sampled parameters; `matrix` is A (original pixel -> augmented pixel)."""

    scale: float
    crop_x: float
    crop_y: float
    flip: bool
    rot_deg: float
    out_w: int
    out_h: int

    @property
    def matrix(self) -> np.ndarray:
        """A `(3, 3) float64` = rotate @ flip @ crop @ resize."""
        S = np.diag([self.scale, self.scale, 1.0])
        C = np.array([[1.0, 0, -self.crop_x], [0, 1.0, -self.crop_y], [0, 0, 1]])
        F = np.array([[-1.0, 0, self.out_w - 1], [0, 1, 0], [0, 0, 1]]) if self.flip else np.eye(3)
        cx, cy = (self.out_w - 1) / 2, (self.out_h - 1) / 2
        a = math.radians(self.rot_deg)
        c, s = math.cos(a), math.sin(a)
        # Rotation about the crop centre: translate to centre, rotate, translate back.
        R = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy], [0, 0, 1]])
        return R @ F @ C @ S


def sample_image_aug(cfg: ImageAugConfig, orig_w: int, orig_h: int, rng: np.random.Generator | None) -> ImageAug:
    """Draw one camera's augmentation (rng unused and may be None when `cfg.train` is False)."""
    base = cfg.width / orig_w
    if cfg.train:
        assert rng is not None
        scale = base + rng.uniform(*cfg.scale_jitter)
    else:
        scale = base
    new_w, new_h = int(orig_w * scale), int(orig_h * scale)
    crop_y = new_h - cfg.height  # keep the bottom of the image
    if cfg.train:
        crop_x = int(rng.integers(0, max(0, new_w - cfg.width) + 1))
        flip = bool(rng.random() < cfg.flip_p)
        rot = float(rng.uniform(-cfg.rot_deg, cfg.rot_deg))
    else:
        crop_x, flip, rot = max(0, new_w - cfg.width) // 2, False, 0.0
    return ImageAug(float(scale), float(crop_x), float(crop_y), flip, rot, cfg.width, cfg.height)


def choose_reduce(scale: float, stored_scale: float, max_upsample: float) -> int:
    """Largest JPEG decode reduction r in (1, 2, 4, 8) whose result needs <= max_upsample enlargement."""
    for r in (8, 4, 2):
        if scale * r / stored_scale <= max_upsample:
            return r
    return 1


def T_decoded_from_original(orig_w: int, orig_h: int, dec_w: int, dec_h: int) -> np.ndarray:
    """`(3, 3) float64` original pixel -> decoded-image pixel, pixel-centre convention.

    A decoded (or re-encoded) image of dec_w columns covers the same extent as the original, so
    u_dec = sx (u + 0.5) - 0.5 with sx = dec_w / orig_w (e.g. a 1/2 DCT decode: u_dec = u / 2 - 0.25).
    """
    sx, sy = dec_w / orig_w, dec_h / orig_h
    return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])


@dataclass(frozen=True)
class BevAugConfig:
    """BEV augmentation; rotation and scale are off by default (flips are exact, they need no resampling)."""

    train: bool = True
    flip_x_p: float = 0.5
    flip_y_p: float = 0.5
    rot_deg: float = 0.0  # U(-rot_deg, rot_deg) about z
    scale: tuple[float, float] = (1.0, 1.0)  # U(lo, hi) on x and y


@dataclass(frozen=True)
class BevAug:
    flip_x: bool = False
    flip_y: bool = False
    rot_deg: float = 0.0
    scale: float = 1.0

    @property
    def matrix(self) -> np.ndarray:
        """M `(4, 4) float64`: key ego -> augmented key ego = rotate @ scale @ flip."""
        F = np.diag([-1.0 if self.flip_x else 1.0, -1.0 if self.flip_y else 1.0, 1.0, 1.0])
        S = np.diag([self.scale, self.scale, 1.0, 1.0])
        a = math.radians(self.rot_deg)
        R = np.eye(4)
        R[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
        return R @ S @ F

    @property
    def is_flip_only(self) -> bool:
        return self.rot_deg == 0.0 and self.scale == 1.0


def sample_bev_aug(cfg: BevAugConfig, rng: np.random.Generator | None) -> BevAug:
    if not cfg.train:
        return BevAug()
    assert rng is not None
    fx = bool(rng.random() < cfg.flip_x_p)
    fy = bool(rng.random() < cfg.flip_y_p)
    rot = float(rng.uniform(-cfg.rot_deg, cfg.rot_deg)) if cfg.rot_deg else 0.0
    scale = float(rng.uniform(*cfg.scale)) if cfg.scale != (1.0, 1.0) else 1.0
    return BevAug(fx, fy, rot, scale)


def _source_cells(aug: BevAug) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each augmented BEV cell: the source cell (nearest) under inv(M) and whether it exists."""
    nx, ny, _ = GRID.shape
    vs = GRID.voxel_size
    cx = GRID.lower[0] + vs * (np.arange(nx) + 0.5)
    cy = GRID.lower[1] + vs * (np.arange(ny) + 0.5)
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    inv = np.linalg.inv(aug.matrix)
    sx = inv[0, 0] * X + inv[0, 1] * Y + inv[0, 3]
    sy = inv[1, 0] * X + inv[1, 1] * Y + inv[1, 3]
    ix = np.floor((sx - GRID.lower[0]) / vs).astype(np.int64)
    iy = np.floor((sy - GRID.lower[1]) / vs).astype(np.int64)
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    return np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1), ok


def apply_bev_aug(grid: np.ndarray, aug: BevAug, fill: int | float, xy_axes: tuple[int, int] = (0, 1)) -> np.ndarray:
    """Move a grid with BEV axes `xy_axes` (e.g. `(200, 200, 16)` or `(C, 200, 200)`) into the augmented
    frame. Flip-only: exact index flips (the grid is symmetric about the key-ego origin). Otherwise
    nearest-cell resampling; cells whose source lies outside the grid get `fill`.
    """
    if aug.is_flip_only:
        flips = tuple(ax for ax, f in zip(xy_axes, (aug.flip_x, aug.flip_y), strict=True) if f)
        return np.ascontiguousarray(np.flip(grid, flips)) if flips else grid
    ix, iy, ok = _source_cells(aug)
    moved = np.moveaxis(grid, xy_axes, (0, 1))
    out = moved[ix, iy]
    out[~ok] = fill
    return np.ascontiguousarray(np.moveaxis(out, (0, 1), xy_axes))
