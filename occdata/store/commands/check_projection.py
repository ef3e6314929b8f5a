"""`occdata check-projection`: the stored depth targets drawn on the 6 images, coloured by depth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from occdata.errors import OccDataError
from occdata.fileio import write_atomic
from occdata.store.reader import StoreReader

__all__ = ["check_image_path", "depth_colors", "draw_projection", "write_image"]


def depth_colors(depth: np.ndarray, max_depth: float = 60.0) -> np.ndarray:
    """`(M,) float` depth -> `(M, 3) uint8` RGB (near: red/yellow, far: blue), turbo-like."""
    t = np.clip(depth / max_depth, 0.0, 1.0)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return lut[(255 * (1.0 - t)).astype(np.int64)]


def draw_projection(reader: StoreReader, index: int, out: Path, reduce: int = 2) -> Path:
    """A 2x3 mosaic (front row, back row) of the images with their LiDAR depth points."""
    check_image_path(out)
    reader.require_done(index)
    images = reader.images(index, reduce=reduce)
    sizes = reader.small("cam/image_size")[index]
    tiles = []
    for img, pts, (w, h) in zip(images, reader.depth_points(index), sizes, strict=True):
        img = img.copy()
        sx, sy = img.shape[1] / w, img.shape[0] / h
        colors = depth_colors(pts[:, 2])
        for (u, v, _), col in zip(pts, colors, strict=True):
            cv2.circle(img, (int(u * sx), int(v * sy)), 1, tuple(int(c) for c in col), -1)
        tiles.append(img)
    order = reader.attrs.get("camera_order", [])
    for tile, name in zip(tiles, order, strict=False):
        cv2.putText(tile, name, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
    h = min(t.shape[0] for t in tiles)
    w = min(t.shape[1] for t in tiles)
    tiles = [t[:h, :w] for t in tiles]
    mosaic = np.vstack([np.hstack(tiles[:3]), np.hstack(tiles[3:])])
    write_image(out, cv2.cvtColor(mosaic, cv2.COLOR_RGB2BGR))
    return out


def check_image_path(out: Path) -> None:
    """Refuse an output name OpenCV has no writer for (e.g. `x.jpgg`) before any work is done."""
    if not out.suffix or not cv2.haveImageWriter(str(out)):
        raise OccDataError(f"cannot write {out}: unknown image type {out.suffix!r} (use .png or .jpg)")


def write_image(out: Path, bgr: np.ndarray) -> None:
    """Write an image atomically: a full disk leaves neither a partial file nor a traceback."""
    check_image_path(out)
    ok, buf = cv2.imencode(out.suffix, bgr)
    if not ok:
        raise OccDataError(f"cannot encode {out}")
    try:
        write_atomic(out, buf.tobytes())
    except OSError as exc:
        raise OccDataError(f"cannot write {out}: {exc.strerror or exc}") from None
