"""Camera and LiDAR observation masks on the voxel grid, with Occ3D's meaning (DESIGN §5.3).

Reusable pure kernels with numpy twins. A voxel grid is `(X, Y, Z)` with lower corner `lower (3,)
float64` (metres, key ego) and cubic voxels of `voxel_size` metres.

The definition (measured against a real Occ3D label; docs/visibility.md has the figures):

- `lidar_ray_mask`: voxels that a LiDAR ray passes through or ends in (3D DDA).
- `lidar_mask`: Occ3D's `mask_lidar`: that traversal plus every object voxel (occupied, not a
  ground class): Occ3D aggregates a whole sequence of sweeps and densifies objects, and on the real
  label 27,040 of 27,042 object voxels are LiDAR-observed while ground and free space are observed
  only where rays reached them.
- `count_occluders`: for each target voxel and one camera, whether its centre projects inside the
  image and how many occluder voxels the segment from the camera centre to that centre crosses
  before it (3D DDA, early exit once `max_occluders` is exceeded).
- `camera_mask`: Occ3D's `mask_camera` from semantics + `mask_lidar`: a LiDAR-observed free or
  ground-surface voxel is camera-visible; a LiDAR-observed object voxel (occupied, not a ground
  class) is camera-visible when, for some camera, its centre is inside the image and at most
  `max_occluders` (default 7) other object voxels lie before it on the ray. On the real label the
  visible fraction falls by ~10% per object voxel crossed (0.97 at 0, 0.50 at 7), as if a 0.4 m
  occupied voxel only partly blocked a ray (our reading: Occ3D traced its rays through sparser
  occupancy than the published, densified labels; its code is not public).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occdata.constants import FREE_LABEL
from occdata.sensors.raycast import segment_advance, segment_setup

__all__ = [
    "GROUND_CLASSES",
    "MAX_OCCLUDERS",
    "camera_mask",
    "clearance_map",
    "count_occluders",
    "lidar_mask",
    "lidar_ray_mask",
    "object_voxels",
]

# driveable_surface, other_flat, sidewalk, terrain: surfaces the camera test does not apply to.
GROUND_CLASSES: tuple[int, ...] = (11, 12, 13, 14)
# Object voxels a camera ray may cross before a voxel stops being visible (docs/visibility.md).
MAX_OCCLUDERS = 7
CLEARANCE_RADIUS = 16  # cap of the empty-space distance map the traversal uses to skip free space


@njit(cache=True)
def _occluders_before(
    occluders: np.ndarray, clearance: np.ndarray, a: np.ndarray, b: np.ndarray, target: np.ndarray,
    lower: np.ndarray, voxel_size: float, shape: np.ndarray, cap: int,
) -> int:
    """Occluder voxels (other than `target (3,)`) crossed by segment a -> b (b inside `target`) before
    the target, counting stops at `cap + 1`. In a voxel with clearance r >= 2 the cube of half-width
    r - 1 voxels around it holds no occluder: unless the target is inside, jump to where the ray leaves it."""
    idx = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_next = np.empty(3)
    t_delta = np.empty(3)
    ok, t_end = segment_setup(a, b, lower, voxel_size, shape, idx, step, t_next, t_delta)
    count = 0
    if not ok:
        return count
    d = b - a
    while True:
        if idx[0] == target[0] and idx[1] == target[1] and idx[2] == target[2]:
            return count
        if occluders[idx[0], idx[1], idx[2]] != 0:
            count += 1
            if count > cap:
                return count
        else:
            r = np.int64(clearance[idx[0], idx[1], idx[2]]) - 1
            if r >= 1 and (abs(target[0] - idx[0]) > r or abs(target[1] - idx[1]) > r or abs(target[2] - idx[2]) > r):
                # Leave the cube idx +- r through the face reached first; t_next of a voxel depends
                # only on its index, so the traversal resumes exactly as the plain DDA would.
                k_exit = 0
                t_exit = np.inf
                for q in range(3):
                    if step[q] != 0:
                        tq = t_next[q] + r * t_delta[q]
                        if tq < t_exit:
                            t_exit, k_exit = tq, q
                if t_exit > t_end:
                    return count
                for q in range(3):
                    if q == k_exit:
                        idx[q] += step[q] * (r + 1)
                    elif step[q] != 0:
                        p = (a[q] + t_exit * d[q] - lower[q]) / voxel_size
                        i = np.int64(np.floor(p))
                        # inside the cube and (the segment being inside the grid here) inside the grid
                        idx[q] = min(max(i, idx[q] - r, 0), idx[q] + r, shape[q] - 1)
                    if step[q] > 0:
                        t_next[q] = (lower[q] + (idx[q] + 1) * voxel_size - a[q]) / d[q]
                    elif step[q] < 0:
                        t_next[q] = (lower[q] + idx[q] * voxel_size - a[q]) / d[q]
                if idx[k_exit] < 0 or idx[k_exit] >= shape[k_exit]:
                    return count
                continue
        if segment_advance(idx, step, t_next, t_delta, shape) > t_end:
            return count


@njit(cache=True)
def clearance_map(occluders: np.ndarray, max_radius: int) -> np.ndarray:
    """`(X, Y, Z) uint8`: L-inf distance in voxels from each voxel to the nearest occluder (0 on an
    occluder), capped at `max_radius`; outside the grid counts as free. Separable exact transform."""
    X, Y, Z = occluders.shape
    big = max_radius
    a = np.empty((X, Y, Z), np.int64)
    for j in range(Y):  # 1D distances along x: two scans
        for k in range(Z):
            last = -10 * big
            for i in range(X):
                if occluders[i, j, k] != 0:
                    last = i
                a[i, j, k] = min(i - last, big)
            last = 10 * big + X
            for i in range(X - 1, -1, -1):
                if occluders[i, j, k] != 0:
                    last = i
                a[i, j, k] = min(a[i, j, k], last - i, big)
    b = np.empty((X, Y, Z), np.int64)
    for i in range(X):  # then y, then z: min over the window of max(offset, distance so far)
        for k in range(Z):
            for j in range(Y):
                m = a[i, j, k]
                for o in range(1, m):
                    if j - o >= 0 and max(o, a[i, j - o, k]) < m:
                        m = max(o, a[i, j - o, k])
                    if j + o < Y and max(o, a[i, j + o, k]) < m:
                        m = max(o, a[i, j + o, k])
                b[i, j, k] = m
    out = np.empty((X, Y, Z), np.uint8)
    for i in range(X):
        for j in range(Y):
            for k in range(Z):
                m = b[i, j, k]
                for o in range(1, m):
                    if k - o >= 0 and max(o, b[i, j, k - o]) < m:
                        m = max(o, b[i, j, k - o])
                    if k + o < Z and max(o, b[i, j, k + o]) < m:
                        m = max(o, b[i, j, k + o])
                out[i, j, k] = m
    return out


@njit(cache=True, parallel=True)
def count_occluders(
    occluders: np.ndarray, clearance: np.ndarray, targets: np.ndarray, T_cam_from_grid: np.ndarray, K: np.ndarray,
    width: int, height: int, lower: np.ndarray, voxel_size: float, cap: int,
) -> np.ndarray:
    """Per target voxel and one camera: -1 if its centre is not inside the image, else the number of
    occluder voxels crossed before it by the ray from the camera centre to that centre (at most
    `cap + 1`: counting stops there). `(M,) int64`.

    occluders `(X, Y, Z) uint8` (1 = blocks); clearance `(X, Y, Z) uint8` = `clearance_map(occluders, r)`
    (lets the traversal skip empty space; any lower values, e.g. all zeros, give the same counts);
    targets `(M, 3) int64` voxel indices;
    `T_cam_from_grid (4, 4) float64`; `K (3, 3) float64`; image `width x height` with pixel centres
    at integer coordinates (the image covers u in [-0.5, W - 0.5), v likewise); `lower (3,) float64`.
    """
    shape = np.array(occluders.shape, np.int64)
    out = np.empty(targets.shape[0], np.int64)
    R = T_cam_from_grid[:3, :3]
    t = T_cam_from_grid[:3, 3]
    cam = np.empty(3)
    for q in range(3):  # camera centre in the grid frame: -R^T t
        cam[q] = -(R[0, q] * t[0] + R[1, q] * t[1] + R[2, q] * t[2])
    for n in prange(targets.shape[0]):
        c = np.empty(3)
        for q in range(3):
            c[q] = lower[q] + (targets[n, q] + 0.5) * voxel_size
        zc = R[2, 0] * c[0] + R[2, 1] * c[1] + R[2, 2] * c[2] + t[2]
        out[n] = -1
        if zc <= 0.0:
            continue
        xc = R[0, 0] * c[0] + R[0, 1] * c[1] + R[0, 2] * c[2] + t[0]
        yc = R[1, 0] * c[0] + R[1, 1] * c[1] + R[1, 2] * c[2] + t[1]
        u = (K[0, 0] * xc + K[0, 1] * yc) / zc + K[0, 2]
        v = K[1, 1] * yc / zc + K[1, 2]
        if u < -0.5 or u >= width - 0.5 or v < -0.5 or v >= height - 0.5:
            continue
        out[n] = _occluders_before(occluders, clearance, cam, c, targets[n], lower, voxel_size, shape, cap)
    return out


def _deep_inside(objects: np.ndarray, depth: int) -> np.ndarray:
    """`(X, Y, Z) bool`: object voxels whose L-inf distance to every non-object voxel (outside the grid
    counts as non-object) exceeds `depth`, i.e. `objects` eroded `depth` times by the 3x3x3 cube."""
    m = objects.copy()
    for _ in range(depth):
        for ax in range(3):
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[ax], hi[ax] = slice(0, -1), slice(1, None)
            nxt = m.copy()
            nxt[tuple(hi)] &= m[tuple(lo)]
            nxt[tuple(lo)] &= m[tuple(hi)]
            idx = [slice(None)] * 3
            for edge in (0, -1):
                idx[ax] = edge
                nxt[tuple(idx)] = False
            m = nxt
    return m


def _camera_mask(
    semantics: np.ndarray, mask_lidar: np.ndarray, K: np.ndarray, T_cam_from_grid: np.ndarray,
    image_size: np.ndarray, lower: np.ndarray, voxel_size: float, max_occluders: int, counter, prefilter: bool,
) -> np.ndarray:
    observed = np.asarray(mask_lidar) != 0
    objects = object_voxels(semantics)
    candidates = objects & observed
    if prefilter:
        # A voxel at L-inf distance d from the nearest non-object voxel is reached by a 6-connected
        # traversal only through >= d - 1 object voxels (one index moves per step): skip the hopeless.
        candidates &= ~_deep_inside(objects, max_occluders + 1)
    targets = np.argwhere(candidates).astype(np.int64)
    occluders = objects.astype(np.uint8)
    clearance = clearance_map(occluders, CLEARANCE_RADIUS) if prefilter else np.zeros(objects.shape, np.uint8)
    lower = np.asarray(lower, np.float64)
    seen = np.zeros(len(targets), bool)
    for c in range(len(K)):
        if seen.all():
            break
        todo = np.flatnonzero(~seen)
        n = counter(occluders, clearance, targets[todo], np.asarray(T_cam_from_grid[c], np.float64),
                    np.asarray(K[c], np.float64), int(image_size[c][0]), int(image_size[c][1]), lower,
                    float(voxel_size), int(max_occluders))
        seen[todo[(n >= 0) & (n <= max_occluders)]] = True
    out = (observed & ~objects).astype(np.uint8)
    out[tuple(targets[seen].T)] = 1
    return out


def camera_mask(
    semantics: np.ndarray, mask_lidar: np.ndarray, K: np.ndarray, T_cam_from_grid: np.ndarray,
    image_size: np.ndarray, lower: np.ndarray, voxel_size: float, max_occluders: int = MAX_OCCLUDERS,
) -> np.ndarray:
    """Occ3D-style `mask_camera` `(X, Y, Z) uint8` 0/1, always within `mask_lidar`.

    semantics `(X, Y, Z) uint8` (FREE_LABEL = free; 255 = unknown, treated as free); mask_lidar
    `(X, Y, Z)` 0/1; K `(C, 3, 3)`; T_cam_from_grid `(C, 4, 4)`; image_size `(C, 2)` (W, H).
    LiDAR-observed free and ground voxels are visible; a LiDAR-observed object voxel is visible
    if some camera sees its centre with at most `max_occluders` object voxels before it (0 = strict).
    """
    return _camera_mask(semantics, mask_lidar, K, T_cam_from_grid, image_size, lower, voxel_size, max_occluders,
                        count_occluders, prefilter=True)


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
        ok, t_end = segment_setup(origins[n], endpoints[n], lower, voxel_size, shape, idx, step, t_next, t_delta)
        if not ok:
            continue
        while True:
            out[idx[0], idx[1], idx[2]] = 1  # benign race: every writer stores 1
            t = segment_advance(idx, step, t_next, t_delta, shape)
            if t > t_end:
                break
    return out


def object_voxels(semantics: np.ndarray) -> np.ndarray:
    """`(X, Y, Z) bool`: occupied voxels that are not a ground class (255 = unknown counts as free)."""
    semantics = np.asarray(semantics)
    return (semantics != FREE_LABEL) & (semantics != 255) & ~np.isin(semantics, GROUND_CLASSES)


def lidar_mask(
    semantics: np.ndarray, origins: np.ndarray, endpoints: np.ndarray, lower: np.ndarray, voxel_size: float
) -> np.ndarray:
    """Occ3D-style `mask_lidar` `(X, Y, Z) uint8` 0/1: voxels the rays `origins (N, 3) -> endpoints
    (N, 3)` (float64, grid frame) pass through or end in, plus every object voxel of `semantics`."""
    shape = np.asarray(np.shape(semantics), np.int64)
    traversed = lidar_ray_mask(np.ascontiguousarray(origins, np.float64), np.ascontiguousarray(endpoints, np.float64),
                               np.asarray(lower, np.float64), float(voxel_size), shape)
    return (traversed | object_voxels(semantics)).astype(np.uint8)
