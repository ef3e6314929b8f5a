"""CPU kernels of the interpolation sampling (numba; their numpy twins are in tests/reference/), used by
`InterpolationSampler` on the CPU in training and eager inference.

The torch path (one `embedding_bag` over a cached index) rebuilds its 4-corner index from ~10 full-size
temporaries whenever the augmentation changes (every training step) and its backward is a scatter into
a few thousand feature rows that torch runs almost serially; together ~0.45 s of a 1 s nano step. Here
the pairs (voxel, camera) are found in two passes over the voxels and the scatter of the backward is
split over threads with private buffers.

Arrays (one batch element b of B, N cameras, V voxels, feature map h x w, C channels):
  points `(V, 3) float32` voxel centres in the augmented key-ego frame;
  cam `(N, 3, 4) float32` rows of T_cam_from_augego; proj `(N, 3, 3) float32` = A K (augmented pixels);
  offsets `(V + 1,) int64` start of each voxel's pairs; rows `(E, 4) int64` feature-table rows of the
  four bilinear corners (table row ((b N + n) h + y) w + x); weights `(E, 4) float32` bilinear weight /
  number of cameras that see the voxel, 0 for a corner outside the map.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["bag_backward", "bag_forward", "bilinear_pairs"]


@numba.njit(cache=True, inline="always")
def _project(p: np.ndarray, cam: np.ndarray, proj: np.ndarray, n: int, H: int, W: int, min_depth: float):
    """Augmented pixel (u, v) of point p in camera n and whether it is visible (as geometry.py's rule)."""
    x = cam[n, 0, 0] * p[0] + cam[n, 0, 1] * p[1] + cam[n, 0, 2] * p[2] + cam[n, 0, 3]
    y = cam[n, 1, 0] * p[0] + cam[n, 1, 1] * p[1] + cam[n, 1, 2] * p[2] + cam[n, 1, 3]
    z = cam[n, 2, 0] * p[0] + cam[n, 2, 1] * p[1] + cam[n, 2, 2] * p[2] + cam[n, 2, 3]
    a = proj[n, 0, 0] * x + proj[n, 0, 1] * y + proj[n, 0, 2] * z
    b = proj[n, 1, 0] * x + proj[n, 1, 1] * y + proj[n, 1, 2] * z
    c = max(proj[n, 2, 0] * x + proj[n, 2, 1] * y + proj[n, 2, 2] * z, np.float32(1e-6))
    u, v = a / c, b / c
    ok = z > min_depth and u >= 0 and u <= W - 1 and v >= 0 and v <= H - 1
    return u, v, ok


@numba.njit(cache=True, parallel=True)
def _count(points, cam, proj, H, W, min_depth):  # noqa: ANN001, ANN202
    counts = np.zeros(points.shape[0], dtype=np.int64)
    for i in numba.prange(points.shape[0]):
        k = 0
        for n in range(cam.shape[0]):
            k += _project(points[i], cam, proj, n, H, W, min_depth)[2]
        counts[i] = k
    return counts


@numba.njit(cache=True, parallel=True)
def _fill(points, cam, proj, H, W, stride, min_depth, h, w, row0, offsets, rows, weights):  # noqa: ANN001, ANN202
    half = np.float32((stride - 1) / 2.0)
    for i in numba.prange(points.shape[0]):
        e = offsets[i]
        seen = offsets[i + 1] - offsets[i]
        for n in range(cam.shape[0]):
            u, v, ok = _project(points[i], cam, proj, n, H, W, min_depth)
            if not ok:
                continue
            fx, fy = (u - half) / stride, (v - half) / stride
            x0, y0 = np.floor(fx), np.floor(fy)
            ax, ay = fx - x0, fy - y0
            for k in range(4):
                xk, yk = int(x0) + (k & 1), int(y0) + (k >> 1)
                wk = (ax if k & 1 else 1 - ax) * (ay if k >> 1 else 1 - ay) / seen
                inside = xk >= 0 and xk < w and yk >= 0 and yk < h
                rows[e, k] = row0 + n * h * w + (yk * w + xk if inside else 0)
                weights[e, k] = wk if inside else 0.0
            e += 1


def bilinear_pairs(points: np.ndarray, cam: np.ndarray, proj: np.ndarray, input_hw: tuple[int, int], stride: int,
                   feat_hw: tuple[int, int], row0: int = 0, min_depth: float = 0.1
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offsets, rows, weights) of one batch element (module doc); pairs in (voxel, camera) order."""
    H, W = input_hw
    counts = _count(points, cam, proj, H, W, np.float32(min_depth))
    offsets = np.zeros(len(points) + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    rows = np.empty((offsets[-1], 4), dtype=np.int64)
    weights = np.empty((offsets[-1], 4), dtype=np.float32)
    _fill(points, cam, proj, H, W, stride, np.float32(min_depth), feat_hw[0], feat_hw[1], row0, offsets, rows,
          weights)
    return offsets, rows, weights


@numba.njit(cache=True, parallel=True)
def bag_forward(table: np.ndarray, offsets: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """out[v] = sum over v's pairs and corners of weight * table[row]: `(V, C) float32`."""
    C = table.shape[1]
    out = np.zeros((len(offsets) - 1, C), dtype=np.float32)
    for v in numba.prange(len(offsets) - 1):
        for e in range(offsets[v], offsets[v + 1]):
            for k in range(4):
                wk = weights[e, k]
                if wk != 0:
                    r = rows[e, k]
                    for c in range(C):
                        out[v, c] += wk * table[r, c]
    return out


@numba.njit(cache=True, parallel=True)
def bag_backward(grad_out: np.ndarray, offsets: np.ndarray, rows: np.ndarray, weights: np.ndarray, n_rows: int,
                 n_chunks: int) -> np.ndarray:
    """The transpose of `bag_forward`: grad_table `(n_rows, C) float32`. Voxel chunks scatter into private
    buffers (no write races), summed at the end."""
    V, C = grad_out.shape
    bufs = np.zeros((n_chunks, n_rows, C), dtype=np.float32)
    step = (V + n_chunks - 1) // n_chunks
    for t in numba.prange(n_chunks):
        for v in range(t * step, min(V, (t + 1) * step)):
            for e in range(offsets[v], offsets[v + 1]):
                for k in range(4):
                    wk = weights[e, k]
                    if wk != 0:
                        r = rows[e, k]
                        for c in range(C):
                            bufs[t, r, c] += wk * grad_out[v, c]
    return bufs.sum(axis=0)
