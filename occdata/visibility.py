"""Voxel-grid ray traversal (3D DDA, Amanatides & Woo): camera visibility and LiDAR observation masks.

Reusable pure kernels (DESIGN §5.3) with numpy twins: a voxel grid is `(X, Y, Z)` with lower corner
`lower (3,) float64` (metres, key ego) and cubic voxels of `voxel_size` metres.

- `camera_visible_mask`: a voxel is visible from a camera if its centre projects inside the image
  (pixel centres at integer coordinates, so the image covers u in [-0.5, W - 0.5), v likewise) with
  positive depth, and no occupied voxel lies strictly between the camera centre and it.
- `lidar_ray_mask`: voxels that a LiDAR ray passes through or ends in.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = [
    "camera_visible_mask",
    "camera_visible_mask_reference",
    "lidar_ray_mask",
    "lidar_ray_mask_reference",
]


@njit(cache=True)
def _dda_setup(
    a: np.ndarray, b: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray,
    idx: np.ndarray, step: np.ndarray, t_next: np.ndarray, t_delta: np.ndarray,
) -> tuple[bool, float]:
    """Clip segment a->b (param t in [0, 1]) to the grid; fill the start voxel `idx`, `step`, next
    boundary `t_next` and `t_delta` (3,) scratch arrays; returns (non-empty, t at the segment end)."""
    d = b - a
    t0, t1 = 0.0, 1.0
    for k in range(3):
        lo = lower[k]
        hi = lower[k] + shape[k] * voxel_size
        if abs(d[k]) < 1e-15:
            if a[k] < lo or a[k] >= hi:
                t0, t1 = 1.0, 0.0
        else:
            ta = (lo - a[k]) / d[k]
            tb = (hi - a[k]) / d[k]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if t0 > t1:
        return False, t1
    for k in range(3):
        step[k] = 0
        t_next[k] = np.inf
        t_delta[k] = np.inf
        p = a[k] + t0 * d[k]
        i = int(np.floor((p - lower[k]) / voxel_size))
        i = min(max(i, 0), shape[k] - 1)
        idx[k] = i
        if d[k] > 0.0:
            step[k] = 1
            t_next[k] = (lower[k] + (i + 1) * voxel_size - a[k]) / d[k]
            t_delta[k] = voxel_size / d[k]
        elif d[k] < 0.0:
            step[k] = -1
            t_next[k] = (lower[k] + i * voxel_size - a[k]) / d[k]
            t_delta[k] = -voxel_size / d[k]
    return True, t1


@njit(cache=True)
def _advance(idx: np.ndarray, step: np.ndarray, t_next: np.ndarray, t_delta: np.ndarray, shape: np.ndarray) -> float:
    """Step into the next voxel along the ray; returns the entry t of the new voxel (inf if it left the grid)."""
    k = 0
    if t_next[1] < t_next[k]:
        k = 1
    if t_next[2] < t_next[k]:
        k = 2
    t_enter = t_next[k]
    idx[k] += step[k]
    t_next[k] += t_delta[k]
    if idx[k] < 0 or idx[k] >= shape[k]:
        return np.inf
    return t_enter


@njit(cache=True)
def _blocked(
    occupied: np.ndarray, ax: float, ay: float, az: float, bx: float, by: float, bz: float,
    ti: int, tj: int, tk: int, lower: np.ndarray, voxel_size: float,
) -> bool:
    """Whether an occupied voxel other than the target (ti, tj, tk) lies on segment a -> b before it.

    Scalar-only 3D DDA (this is the hot loop of the camera mask)."""
    X, Y, Z = occupied.shape
    dx, dy, dz = bx - ax, by - ay, bz - az
    t0, t1 = 0.0, 1.0
    for k in range(3):
        o = ax if k == 0 else ay if k == 1 else az
        d = dx if k == 0 else dy if k == 1 else dz
        n = X if k == 0 else Y if k == 1 else Z
        lo = lower[k]
        hi = lo + n * voxel_size
        if abs(d) < 1e-15:
            if o < lo or o >= hi:
                return False
        else:
            ta = (lo - o) / d
            tb = (hi - o) / d
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if t0 > t1:
        return False
    i = min(max(int(np.floor((ax + t0 * dx - lower[0]) / voxel_size)), 0), X - 1)
    j = min(max(int(np.floor((ay + t0 * dy - lower[1]) / voxel_size)), 0), Y - 1)
    k = min(max(int(np.floor((az + t0 * dz - lower[2]) / voxel_size)), 0), Z - 1)
    inf = np.inf
    si = 1 if dx > 0.0 else -1 if dx < 0.0 else 0
    sj = 1 if dy > 0.0 else -1 if dy < 0.0 else 0
    sk = 1 if dz > 0.0 else -1 if dz < 0.0 else 0
    ni = (lower[0] + (i + (si > 0)) * voxel_size - ax) / dx if si != 0 else inf
    nj = (lower[1] + (j + (sj > 0)) * voxel_size - ay) / dy if sj != 0 else inf
    nk = (lower[2] + (k + (sk > 0)) * voxel_size - az) / dz if sk != 0 else inf
    di = voxel_size / abs(dx) if si != 0 else inf
    dj = voxel_size / abs(dy) if sj != 0 else inf
    dk = voxel_size / abs(dz) if sk != 0 else inf
    while True:
        if i == ti and j == tj and k == tk:
            return False
        if occupied[i, j, k] != 0:
            return True
        if ni <= nj and ni <= nk:
            t = ni
            i += si
            ni += di
            if i < 0 or i >= X:
                return False
        elif nj <= nk:
            t = nj
            j += sj
            nj += dj
            if j < 0 or j >= Y:
                return False
        else:
            t = nk
            k += sk
            nk += dk
            if k < 0 or k >= Z:
                return False
        if t > t1:
            return False


@njit(cache=True, parallel=True)
def camera_visible_mask(
    occupied: np.ndarray, T_cam_from_grid: np.ndarray, K: np.ndarray, width: int, height: int,
    lower: np.ndarray, voxel_size: float,
) -> np.ndarray:
    """Voxels visible from one camera, `(X, Y, Z) uint8` 0/1.

    `occupied (X, Y, Z) uint8` (1 = occupied), `T_cam_from_grid (4, 4) float64` (grid frame, e.g.
    key ego -> camera), `K (3, 3) float64`, image `width x height`, `lower (3,) float64`.
    """
    X, Y, Z = occupied.shape
    out = np.zeros((X, Y, Z), np.uint8)
    R = T_cam_from_grid[:3, :3]
    t = T_cam_from_grid[:3, 3]
    # Camera centre in the grid frame: -R^T t.
    cam = np.empty(3)
    for a in range(3):
        cam[a] = -(R[0, a] * t[0] + R[1, a] * t[1] + R[2, a] * t[2])
    for i in prange(X):
        c = np.empty(3)
        for j in range(Y):
            for k in range(Z):
                c[0] = lower[0] + (i + 0.5) * voxel_size
                c[1] = lower[1] + (j + 0.5) * voxel_size
                c[2] = lower[2] + (k + 0.5) * voxel_size
                zc = R[2, 0] * c[0] + R[2, 1] * c[1] + R[2, 2] * c[2] + t[2]
                if zc <= 0.0:
                    continue
                xc = R[0, 0] * c[0] + R[0, 1] * c[1] + R[0, 2] * c[2] + t[0]
                yc = R[1, 0] * c[0] + R[1, 1] * c[1] + R[1, 2] * c[2] + t[1]
                u = (K[0, 0] * xc + K[0, 1] * yc) / zc + K[0, 2]
                v = K[1, 1] * yc / zc + K[1, 2]
                if u < -0.5 or u >= width - 0.5 or v < -0.5 or v >= height - 0.5:
                    continue
                if not _blocked(occupied, cam[0], cam[1], cam[2], c[0], c[1], c[2], i, j, k, lower, voxel_size):
                    out[i, j, k] = 1
    return out


def _segment_hits_boxes(a: np.ndarray, b: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray) -> np.ndarray:
    """Whether segment a->b intersects each closed box `(M, 3)`; `(M,) bool` (slab test)."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (box_lo - a) / d
        tb = (box_hi - a) / d
    t_lo = np.where(np.abs(d) < 1e-15, -np.inf, np.minimum(ta, tb))
    t_hi = np.where(np.abs(d) < 1e-15, np.inf, np.maximum(ta, tb))
    par_out = (np.abs(d) < 1e-15) & ((a < box_lo) | (a > box_hi))
    t0 = np.maximum(t_lo.max(axis=1), 0.0)
    t1 = np.minimum(t_hi.min(axis=1), 1.0)
    return (t0 <= t1) & ~par_out.any(axis=1)


def camera_visible_mask_reference(
    occupied: np.ndarray, T_cam_from_grid: np.ndarray, K: np.ndarray, width: int, height: int,
    lower: np.ndarray, voxel_size: float,
) -> np.ndarray:
    """Numpy twin of `camera_visible_mask`: per voxel, a segment-vs-box test against every occupied voxel."""
    shape = np.array(occupied.shape)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    centres = lower + (grid + 0.5) * voxel_size
    R, t = T_cam_from_grid[:3, :3], T_cam_from_grid[:3, 3]
    pc = centres @ R.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (K[0, 0] * pc[:, 0] + K[0, 1] * pc[:, 1]) / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
    inside = (pc[:, 2] > 0) & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    cam = -(R.T @ t)
    occ_idx = np.argwhere(occupied != 0)
    lo = lower + occ_idx * voxel_size
    hi = lo + voxel_size
    out = np.zeros(len(grid), np.uint8)
    for n in np.flatnonzero(inside):
        others = ~(occ_idx == grid[n]).all(axis=1)
        out[n] = not _segment_hits_boxes(cam, centres[n], lo[others], hi[others]).any()
    return out.reshape(occupied.shape)


@njit(cache=True, parallel=True)
def lidar_ray_mask(
    origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray
) -> np.ndarray:
    """Voxels traversed by LiDAR rays `origins (N, 3) -> endpoints (N, 3)` (float64, grid frame),
    end voxel included; `(X, Y, Z) uint8` 0/1 for `shape (3,) int64`."""
    out = np.zeros((shape[0], shape[1], shape[2]), np.uint8)
    for n in prange(origins.shape[0]):
        idx = np.empty(3, np.int64)
        step = np.empty(3, np.int64)
        t_next = np.empty(3)
        t_delta = np.empty(3)
        ok, t_end = _dda_setup(origins[n], endpoints[n], lower, voxel_size, shape, idx, step, t_next, t_delta)
        if not ok:
            continue
        while True:
            out[idx[0], idx[1], idx[2]] = 1  # benign race: every writer stores 1
            t = _advance(idx, step, t_next, t_delta, shape)
            if t > t_end:
                break
    return out


def lidar_ray_mask_reference(
    origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float, shape: np.ndarray
) -> np.ndarray:
    """Numpy twin of `lidar_ray_mask`: segment-vs-box test of every ray against every voxel."""
    shape = np.asarray(shape)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    lo = lower + grid * voxel_size
    hi = lo + voxel_size
    out = np.zeros(len(grid), np.uint8)
    for a, b in zip(origins, endpoints, strict=True):
        out |= _segment_hits_boxes(np.asarray(a, np.float64), np.asarray(b, np.float64), lo, hi).astype(np.uint8)
    return out.reshape(tuple(shape))
