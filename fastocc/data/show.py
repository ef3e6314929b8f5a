"""`fastocc show-batch`: one sample as the network sees it, drawn so that misalignment is visible.

Top: the N augmented input images (rows of 3, the store's camera order) with their depth targets
(one dot per 16x16 patch, colour = depth).
Below: BEV of the voxel labels (top-most non-free class), the BEV multi-hot GT, both in the augmented
frame, with the depth-target points lifted back to 3D through A, K, T_keyego_from_cam and M drawn on
top (white): they must lie on the labelled structures, whatever the augmentation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fastocc.data.batch import Batch
from fastocc.data.dataset import load_batch
from fastocc.data.sample import SampleConfig
from occdata.constants import CLASS_COLORS, FREE_LABEL, GRID
from occdata.sensors.image_ops import IMAGENET_MEAN, IMAGENET_STD
from occdata.store.commands.check_projection import check_image_path, write_image

__all__ = ["ShowConfig", "lift_depth_targets", "render_batch", "show_batch"]

_BEV_SCALE = 2  # pixels per BEV cell


@dataclass(frozen=True)
class ShowConfig:
    store: str | Path
    out: Path
    index: int = 0
    seed: int = 0
    sample: SampleConfig = field(default_factory=SampleConfig)


def lift_depth_targets(batch: Batch, k: int = 0, stride: int = 16) -> np.ndarray:
    """Depth-target patch centres of sample k as 3D points in the AUGMENTED key-ego frame, `(P, 3) float64`."""
    pts = []
    M = batch.bev_aug[k].double().numpy()
    for c in range(batch.depth_target.shape[1]):
        d = batch.depth_target[k, c].double().numpy()
        ys, xs = np.nonzero(d)
        if not len(xs):
            continue
        uv_img = np.stack([xs * stride + (stride - 1) / 2, ys * stride + (stride - 1) / 2, np.ones(len(xs))])
        uv_orig = np.linalg.inv(batch.img_aug[k, c].double().numpy()) @ uv_img
        p_cam = np.linalg.inv(batch.K[k, c].double().numpy()) @ uv_orig * d[ys, xs]
        T = batch.T_keyego_from_cam[k, c].double().numpy()
        p = M @ T @ np.vstack([p_cam, np.ones(len(xs))])
        pts.append(p[:3].T)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def _bev_canvas(rgb_xy: np.ndarray) -> np.ndarray:
    """`(X, Y, 3)` -> image with x (forward) up and y (left) to the left."""
    img = rgb_xy[::-1, ::-1]
    return cv2.resize(np.ascontiguousarray(img), None, fx=_BEV_SCALE, fy=_BEV_SCALE,
                      interpolation=cv2.INTER_NEAREST)


def _draw_points(canvas: np.ndarray, pts: np.ndarray) -> None:
    nx, ny, _ = GRID.shape
    ij = GRID.index_of(pts)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
    for i, j in ij[ok, :2]:
        cv2.circle(canvas, (int((ny - 1 - j) * _BEV_SCALE), int((nx - 1 - i) * _BEV_SCALE)), 1, (255, 255, 255), -1)


def _tile_rows(tiles: list[np.ndarray], per_row: int = 3) -> np.ndarray:
    """Equal-size tiles in rows of `per_row` (nuScenes' 6: front row, back row); a short last row is
    padded with black tiles."""
    blank = np.zeros_like(tiles[0])
    padded = tiles + [blank] * (-len(tiles) % per_row)
    return np.vstack([np.hstack(padded[r:r + per_row]) for r in range(0, len(padded), per_row)])


def render_batch(batch: Batch, k: int = 0) -> np.ndarray:
    """The picture for sample k, RGB uint8."""
    colors = np.array(CLASS_COLORS, dtype=np.uint8)
    mean, std = np.array(IMAGENET_MEAN), np.array(IMAGENET_STD)
    tiles = []
    for c in range(batch.images.shape[1]):
        img = batch.images[k, c].numpy().transpose(1, 2, 0) * std + mean
        img = np.ascontiguousarray(np.clip(img, 0, 255).astype(np.uint8))
        d = batch.depth_target[k, c].numpy()
        stride = img.shape[0] // d.shape[0]
        ys, xs = np.nonzero(d)
        vals = np.clip(d[ys, xs] / 45.0 * 255, 0, 255).astype(np.uint8)[:, None]
        cols = cv2.applyColorMap(vals, cv2.COLORMAP_JET)[:, 0, ::-1].tolist()  # BGR -> RGB
        for y, x, col in zip(ys, xs, cols, strict=True):
            cv2.circle(img, (int(x) * stride + stride // 2, int(y) * stride + stride // 2), 2, col, -1)
        cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), (255, 255, 255), 1)
        tiles.append(img)
    left = _tile_rows(tiles)
    sem = batch.semantics[k].numpy()
    # Top-most non-free, non-ignore label per column.
    occ = (sem != FREE_LABEL) & (sem != 255)
    top = np.where(occ.any(-1), np.take_along_axis(sem, (15 - np.argmax(occ[..., ::-1], -1))[..., None], -1)[..., 0], 0)
    sem_rgb = np.where(occ.any(-1)[..., None], colors[np.clip(top, 0, 16)], 40).astype(np.uint8)
    bev = batch.bev_target[k].numpy()[:FREE_LABEL]  # (17, X, Y), free not drawn
    n = bev.sum(0)
    gt_rgb = (np.tensordot(bev, colors[:FREE_LABEL].astype(np.float64), axes=(0, 0)) / np.maximum(n, 1)[..., None])
    gt_rgb = np.where((n > 0)[..., None], gt_rgb, 40).astype(np.uint8)
    pts = lift_depth_targets(batch, k)
    panels = []
    for rgb, title in ((sem_rgb, "labels (top view)"), (gt_rgb, "BEV GT")):
        canvas = np.ascontiguousarray(_bev_canvas(rgb))
        _draw_points(canvas, pts)
        cx = canvas.shape[1] // 2
        cv2.arrowedLine(canvas, (cx, cx + 12), (cx, cx - 12), (255, 255, 255), 2, tipLength=0.4)  # ego, forward
        cv2.putText(canvas, title, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        panels.append(canvas)
    right = np.hstack([panels[0], np.full((panels[0].shape[0], 8, 3), 255, np.uint8), panels[1]])
    w = max(left.shape[1], right.shape[1])
    pad = lambda a: np.pad(a, ((0, 0), (0, w - a.shape[1]), (0, 0)))  # noqa: E731
    out = np.vstack([pad(left), np.full((8, w, 3), 255, np.uint8), pad(right)])
    i = int(batch.sample_index[k])
    M = batch.bev_aug[k].numpy()
    note = (f"sample {i}  labels={'yes' if batch.has_labels[k] else 'no'}  BEV flip x={M[0, 0] < 0} "
            f"y={M[1, 1] < 0}  white dots: depth targets lifted through inv(A), K, T, M")
    footer = np.zeros((24, out.shape[1], 3), np.uint8)
    cv2.putText(footer, note, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
    return np.vstack([out, footer])


def show_batch(cfg: ShowConfig) -> Path:
    check_image_path(cfg.out)
    batch = load_batch(cfg.store, [cfg.index], cfg.sample, seed=cfg.seed)
    img = render_batch(batch)
    write_image(cfg.out, cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return cfg.out
