"""Pictures of occupancy grids (numpy + OpenCV, no GUI toolkit, no model): a z-buffered voxel renderer
seen from an oblique viewpoint, a BEV top view, and the prediction-beside-truth picture of
`fastocc predict --png`.

The voxel renderer is orthographic. Only the voxel faces that look towards the viewer AND border a free
(or out-of-grid) voxel are drawn. Each such face is sampled on an S x S grid of points (S from the
on-screen voxel size, so every pixel of a face gets at least one sample), the points are projected and
the nearest one per pixel wins (a z-buffer by sort, no per-voxel Python loop). Faces are shaded by
orientation (top brightest) and their border samples darkened, so that single voxels stay readable.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from occdata.constants import CLASS_COLORS, CLASS_NAMES, EGO_BOX, FREE_LABEL, GRID, NUM_CLASSES, OccGrid

__all__ = [
    "EGO_COLOR",
    "View",
    "bev_top_view",
    "class_legend",
    "prediction_picture",
    "render_voxels",
]

EGO_COLOR = (110, 110, 110)  # the ego car's box (not a class colour)
_EGO = NUM_CLASSES  # the ego car's voxels in a drawn grid: the label after the classes
_BACKGROUND = (255, 255, 255)
_SHADE = {"top": 1.0, "x": 0.8, "y": 0.62, "bottom": 0.45}
_UNSEEN = 185.0  # grey of BEV columns outside the camera mask
_EDGE = 0.7  # border samples of a face are this much darker
_PALETTE = np.array(CLASS_COLORS, dtype=np.uint8)


@dataclass(frozen=True)
class View:
    """Oblique orthographic viewpoint. `azimuth_deg`: where the viewer stands around the car, measured in
    the key-ego xy plane from -x (0 = straight behind, positive = towards the car's right, -y);
    `elevation_deg`: the viewer's height angle above the ground plane."""

    azimuth_deg: float = 20.0
    elevation_deg: float = 50.0

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, up, into) unit vectors in key ego: screen x, screen y (up) and view direction."""
        a, e = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        to_viewer = np.array([-math.cos(a) * math.cos(e), -math.sin(a) * math.cos(e), math.sin(e)])
        into = -to_viewer
        right = np.cross(into, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, into)
        return right, up, into


def _with_ego(occ_labels: np.ndarray, grid: OccGrid) -> tuple[np.ndarray, np.ndarray]:
    """Label grid -> (labels, colour table) with the free voxels of the ego car (`EGO_BOX`) as label `_EGO`."""
    labels = occ_labels.copy()
    centers = grid.voxel_centers()
    lo, hi = np.array(EGO_BOX[0]), np.array(EGO_BOX[1])
    ego = ((centers > lo) & (centers < hi)).all(axis=-1)
    labels[ego & (labels == FREE_LABEL)] = _EGO
    palette = np.vstack([_PALETTE, np.array([EGO_COLOR], dtype=np.uint8)])
    return labels, palette


@dataclass(frozen=True)
class _Screen:
    """The orthographic projection of a grid into an image: screen = (ox + scale * p.right,
    oy - scale * p.up) in pixels, for an `(H, W)` image."""

    right: np.ndarray
    up: np.ndarray
    into: np.ndarray
    scale: float
    ox: float
    oy: float
    H: int
    W: int


def _screen(grid: OccGrid, view: View, H: int, W: int, margin: int = 6) -> _Screen:
    """Fit the grid's 8 corners into the image (independent of content)."""
    right, up, into = view.axes()
    corners = np.array([[x, y, z] for x in (grid.lower[0], grid.upper[0]) for y in (grid.lower[1], grid.upper[1])
                        for z in (grid.lower[2], grid.upper[2])])
    sx, sy = corners @ right, corners @ up
    scale = min((W - 2 * margin) / (sx.max() - sx.min()), (H - 2 * margin) / (sy.max() - sy.min()))
    ox = margin + ((W - 2 * margin) - scale * (sx.max() - sx.min())) / 2 - scale * sx.min()
    oy = margin + ((H - 2 * margin) - scale * (sy.max() - sy.min())) / 2 + scale * sy.max()
    return _Screen(right, up, into, scale, ox, oy, H, W)


def _face_samples(lab: np.ndarray, palette: np.ndarray, grid: OccGrid, scr: _Screen
                  ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Sample points of every exposed voxel face that looks towards the viewer: per face direction,
    their pixel index, depth and shaded colour (only the samples inside the image)."""
    occ = lab != FREE_LABEL
    vs = grid.voxel_size
    lower = np.asarray(grid.lower, dtype=np.float64)
    n_sub = max(2, int(math.ceil(1.5 * scr.scale * vs)) + 1)  # samples per face edge: no holes between them
    pad = np.pad(occ, 1, constant_values=False)
    t = (np.arange(n_sub) + 0.5) / n_sub - 0.5  # face-local sample offsets in voxel units
    su, sv = np.meshgrid(t, t, indexing="ij")
    edge = ((np.abs(su) > 0.5 - 0.75 / n_sub) | (np.abs(sv) > 0.5 - 0.75 / n_sub)).ravel()
    px_all, depth_all, color_all = [], [], []
    for axis in range(3):
        for sign in (-1, 1):
            normal = np.zeros(3)
            normal[axis] = sign
            if normal @ scr.into >= 0:  # faces away from the viewer
                continue
            sl = [slice(1, -1)] * 3
            sl[axis] = slice(1 + sign, pad.shape[axis] - 1 + sign)
            ijk = np.argwhere(occ & ~pad[tuple(sl)])  # faces with no occupied neighbour in front
            if not len(ijk):
                continue
            a1, a2 = [d for d in range(3) if d != axis]
            centre = lower + vs * (ijk + 0.5) + 0.5 * vs * normal  # face centres (F, 3)
            pts = np.repeat(centre[:, None, :], n_sub * n_sub, axis=1)
            pts[..., a1] += vs * su.ravel()
            pts[..., a2] += vs * sv.ravel()
            shade = _SHADE["top"] if axis == 2 and sign > 0 else _SHADE["bottom"] if axis == 2 else _SHADE[
                "x" if axis == 0 else "y"]
            base = palette[lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]]].astype(np.float32) * shade  # (F, 3)
            col = np.repeat(base[:, None, :], n_sub * n_sub, axis=1)
            col[:, edge] *= _EDGE
            u = np.floor(scr.ox + scr.scale * (pts @ scr.right)).astype(np.int64).ravel()
            v = np.floor(scr.oy - scr.scale * (pts @ scr.up)).astype(np.int64).ravel()
            ok = (u >= 0) & (u < scr.W) & (v >= 0) & (v < scr.H)
            px_all.append((v * scr.W + u)[ok])
            depth_all.append((pts @ scr.into).ravel()[ok])
            color_all.append(col.reshape(-1, 3)[ok])
    return px_all, depth_all, color_all


def render_voxels(
    labels: np.ndarray,
    size: tuple[int, int] = (600, 800),
    view: View = View(),  # noqa: B008 - frozen, immutable default
    mask: np.ndarray | None = None,
    grid: OccGrid = GRID,
    ego: bool = True,
) -> np.ndarray:
    """Draw a `(X, Y, Z) uint8` label grid as coloured cubes; returns `(H, W, 3) uint8` RGB for
    `size = (H, W)`. Free (17) and labels >= 18 are empty; with `mask` (0/1, same shape) voxels where
    it is 0 are empty too. The whole grid is fitted into the image, so pictures of different grids with
    the same size and view line up pixel for pixel."""
    H, W = size
    lab = np.asarray(labels)
    if lab.shape != grid.shape:
        raise ValueError(f"labels have shape {lab.shape}, expected {grid.shape}")
    lab = np.where(lab < FREE_LABEL, lab, FREE_LABEL).astype(np.uint8)
    if mask is not None:
        lab = np.where(np.asarray(mask) > 0, lab, FREE_LABEL).astype(np.uint8)
    palette = _PALETTE
    if ego:
        lab, palette = _with_ego(lab, grid)
    img = np.empty((H, W, 3), dtype=np.uint8)
    img[:] = _BACKGROUND
    px_all, depth_all, color_all = _face_samples(lab, palette, grid, _screen(grid, view, H, W))
    if px_all:  # per pixel, the nearest sample's colour
        px, depth, color = np.concatenate(px_all), np.concatenate(depth_all), np.concatenate(color_all)
        order = np.lexsort((depth, px))
        px, color = px[order], color[order]
        first = np.ones(len(px), dtype=bool)
        first[1:] = px[1:] != px[:-1]
        img.reshape(-1, 3)[px[first]] = np.clip(color[first], 0, 255).astype(np.uint8)
    return img


def bev_top_view(labels: np.ndarray, mask: np.ndarray | None = None, cell_px: int = 2,
                 voxel_size: float | None = GRID.voxel_size) -> np.ndarray:
    """Top view `(X*cell_px, Y*cell_px, 3) uint8` RGB: per column the colour of the highest non-free
    label (white where the column is free), x (forward) up, y (left) to the left, ego at the centre
    (black outline, drawn for `voxel_size` m voxels; None: no outline, e.g. a grid in another frame).
    With `mask` (0/1 per voxel), columns with no visible voxel are greyed (free ones plain grey,
    occupied ones a greyed class colour)."""
    lab = np.asarray(labels)
    X, Y, Z = lab.shape
    occ = lab < FREE_LABEL
    top = Z - 1 - np.argmax(occ[:, :, ::-1], axis=2)  # highest occupied z per column
    col_lab = np.where(occ.any(2), np.take_along_axis(lab, top[..., None], 2)[..., 0], FREE_LABEL)
    rgb = _PALETTE[np.minimum(col_lab, FREE_LABEL)].astype(np.float32)
    seen = None
    if mask is not None:
        seen = (np.asarray(mask) > 0).any(2)
        rgb[~seen] = 0.6 * rgb[~seen] + 0.4 * _UNSEEN
        rgb[~seen & (col_lab == FREE_LABEL)] = _UNSEEN
    img = np.ascontiguousarray(rgb[::-1, ::-1].astype(np.uint8))  # rows: +x first; cols: +y first
    img = cv2.resize(img, (Y * cell_px, X * cell_px), interpolation=cv2.INTER_NEAREST)
    if voxel_size is None:
        return img
    # Ego box, 4.4 x 2 m at the grid centre.
    cx, cy = X * cell_px / 2, Y * cell_px / 2
    px_per_m = cell_px / voxel_size
    cv2.rectangle(img, (int(cy - 1.0 * px_per_m), int(cx - 2.2 * px_per_m)),
                  (int(cy + 1.0 * px_per_m), int(cx + 2.2 * px_per_m)), (0, 0, 0), 1)
    return img


def class_legend(classes: Sequence[int], width: int, row_h: int = 22) -> np.ndarray:
    """A white panel listing the given classes with their colour swatches, `(rows*row_h, width, 3)`."""
    cols = max(1, width // 200)
    rows = max(1, math.ceil(len(classes) / cols))
    img = np.full((rows * row_h + 8, width, 3), 255, dtype=np.uint8)
    for k, c in enumerate(classes):
        r, q = divmod(k, cols)
        x, y = 8 + q * (width // cols), 4 + r * row_h
        color = EGO_COLOR if c == _EGO else tuple(int(v) for v in _PALETTE[c])
        cv2.rectangle(img, (x, y + 3), (x + 16, y + row_h - 5), color, -1)
        cv2.rectangle(img, (x, y + 3), (x + 16, y + row_h - 5), (0, 0, 0), 1)
        name = "ego" if c == _EGO else CLASS_NAMES[c]
        cv2.putText(img, name, (x + 22, y + row_h - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _title(img: np.ndarray, text: str) -> np.ndarray:
    out = np.ascontiguousarray(img.copy())
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 2)
    cv2.rectangle(out, (0, 0), (w + 12, h + 12), (255, 255, 255), -1)
    cv2.putText(out, text, (6, h + 6), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 2, cv2.LINE_AA)
    return out


def _fit(img: np.ndarray, w: int) -> np.ndarray:
    h = max(1, round(img.shape[0] * w / img.shape[1]))
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)


def _pad_to(img: np.ndarray, w: int) -> np.ndarray:
    if img.shape[1] >= w:
        return img[:, :w]
    out = np.full((img.shape[0], w, 3), 255, dtype=np.uint8)
    out[:, : img.shape[1]] = img
    return out


def prediction_picture(
    images: Sequence[np.ndarray],
    pred: np.ndarray,
    gt: np.ndarray | None,
    mask_camera: np.ndarray | None,
    camera_names: Sequence[str] = (),
    title: str = "",
    width: int = 1600,
    names: tuple[str, str] = ("prediction", "ground truth"),
) -> np.ndarray:
    """The `fastocc predict --png` picture, `(H, width, 3) uint8` RGB, top to bottom (`names`: the
    titles of the two label panels):

    - the camera images in rows of 3 (nuScenes' 6: front row, back row; the store's camera order), if given;
    - 3D voxel renderings of prediction | ground truth (whole grid, same viewpoint and scale);
    - BEV top views of prediction | ground truth, columns outside the camera mask greyed (the official
      mIoU scores only camera-visible voxels);
    - a legend of the classes present.
    Without ground truth (test split) the truth panels are left blank and say so.
    """
    third = width // 3
    cams = []
    if len(images):
        tiles = [_fit(img, third) for img in images]
        for tile, name in zip(tiles, camera_names, strict=False):
            cv2.putText(tile, name, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 2, cv2.LINE_AA)
        h = min(t.shape[0] for t in tiles)
        tiles = [t[:h] for t in tiles]
        # rows of 3 (nuScenes' 6: front row, back row), each padded to the width: any camera count
        cams = [np.vstack([_pad_to(np.hstack(tiles[r:r + 3]), width) for r in range(0, len(tiles), 3)])]

    half = width // 2
    size3d = (round(half * 0.75), half)
    m = mask_camera
    pred3d = _title(render_voxels(pred, size3d), names[0])
    if gt is not None:
        gt3d = _title(render_voxels(gt, size3d), names[1])
    else:
        gt3d = _title(np.full_like(pred3d, 255), f"{names[1]}: none (unlabelled sample)")
    row3d = _pad_to(np.hstack([pred3d, gt3d]), width)

    cell = max(1, min(half // pred.shape[1], 3))
    bev_p = _title(bev_top_view(pred, m, cell), f"{names[0]}, top view")
    bev_g = _title(bev_top_view(gt, m, cell), f"{names[1]}, top view") if gt is not None else np.full_like(bev_p, 255)
    pad = np.full((bev_p.shape[0], half - bev_p.shape[1], 3), 255, dtype=np.uint8)
    bev_row = np.hstack([bev_p, pad, bev_g, pad[:, : max(0, width - half - bev_g.shape[1])]])
    bev_row = _pad_to(bev_row, width)

    present = sorted({int(c) for g in (pred, gt) if g is not None for c in np.unique(g) if c < FREE_LABEL})
    legend = class_legend(present + [_EGO], width)
    note = "top views: grey = outside the camera mask" if m is not None else ""
    parts = [*cams, row3d, bev_row, legend]
    if title or note:
        head = np.full((30, width, 3), 255, dtype=np.uint8)
        cv2.putText(head, "   ".join(t for t in (title, note) if t), (8, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                    (0, 0, 0), 1, cv2.LINE_AA)
        parts.insert(0, head)
    return np.ascontiguousarray(np.vstack(parts))
