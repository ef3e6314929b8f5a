"""A nuScenes-format tree whose cameras differ in size, derived honestly from a synthetic world: one
camera's JPEGs are resampled to another size (and aspect ratio), its intrinsics scaled to match in the
pixel-centre convention, its sample_data rows given the new width and height, and the world's rendered
depth maps of it (`depth/<sample_data token>.npy`, the synthetic truth) resampled the same way (nearest)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

__all__ = ["resize_camera", "scaled_intrinsics"]


def scaled_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """`(3, 3) float64` K of an image resampled by (sx, sy) over the same extent: u' = sx (u + 0.5) - 0.5."""
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return S @ K


def resize_camera(src: Path, dst: Path, channel: str, width: int, height: int) -> Path:
    """Copy the tree `src` to `dst` with camera `channel` resampled to `width x height` (every JPEG of it,
    its calibrated_sensor intrinsics, its sample_data sizes). Returns `dst`."""
    shutil.copytree(src, dst)
    tables = next(p for p in dst.iterdir() if p.is_dir() and (p / "sensor.json").is_file())
    sensor = next(s["token"] for s in json.loads((tables / "sensor.json").read_text()) if s["channel"] == channel)
    calib = json.loads((tables / "calibrated_sensor.json").read_text())
    rows = json.loads((tables / "sample_data.json").read_text())
    mine = {c["token"] for c in calib if c["sensor_token"] == sensor}
    sizes = {(r["width"], r["height"]) for r in rows if r["calibrated_sensor_token"] in mine}
    assert len(sizes) == 1, sizes
    (w0, h0), = sizes
    for c in calib:
        if c["token"] in mine:
            c["camera_intrinsic"] = scaled_intrinsics(np.asarray(c["camera_intrinsic"]), width / w0,
                                                      height / h0).tolist()
    for r in rows:
        if r["calibrated_sensor_token"] in mine:
            path = dst / r["filename"]
            img = cv2.imread(str(path), cv2.IMREAD_COLOR)
            assert img is not None and img.shape[:2] == (h0, w0), path
            # INTER_AREA / INTER_LINEAR map pixel centres as `scaled_intrinsics` does
            cv2.imwrite(str(path), cv2.resize(img, (width, height), interpolation=cv2.INTER_LINEAR),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
            r["width"], r["height"] = width, height
            truth = dst / "depth" / f"{r['token']}.npy"
            if truth.is_file():  # nearest, pixel-centre aligned: no blending across depth edges
                d = np.load(truth, allow_pickle=False)
                np.save(truth, cv2.resize(d, (width, height), interpolation=cv2.INTER_NEAREST_EXACT))
    (tables / "calibrated_sensor.json").write_text(json.dumps(calib))
    (tables / "sample_data.json").write_text(json.dumps(rows))
    return dst
