"""Ray casting of the synthetic world: cameras (depth + shaded RGB) and the spinning LiDAR.

Acceleration structure: a 2D uniform grid over the ground plane lists the primitives whose xy
bounds overlap each cell; a ray walks the cells with a 2D DDA and stops at the first cell whose
exit distance is beyond the closest hit so far, at the ground plane z = 0, or where it climbs
above the tallest primitive. Every numba kernel has a plain numpy twin (`*_reference`, in
tests/reference/synth_render.py) that the tests compare it with.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = [
    "HIT_GROUND",
    "HIT_NONE",
    "SKY_CLASS",
    "SUN_DIR",
    "build_cell_grid",
    "cast_rays",
    "hit_normals",
    "palette_tables",
    "render_camera_kernel",
]

HIT_NONE, HIT_GROUND = -1, -2
SKY_CLASS = 255  # `render_camera_kernel`'s class where a pixel sees nothing (no Occ3D class)
_EPS_T = 1e-9
SUN_DIR = np.array([0.40, 0.30, 0.866], np.float64) / np.linalg.norm([0.40, 0.30, 0.866])


# --------------------------------------------------------------------------------------------
# 2D cell grid over primitives
# --------------------------------------------------------------------------------------------
@njit(cache=True)
def _xy_extent(p: np.ndarray) -> tuple[float, float]:
    if p[0] == 0.0:  # box: half extents of the rotated rectangle's axis-aligned bounds
        return abs(p[3]) * p[5] + abs(p[4]) * p[6], abs(p[4]) * p[5] + abs(p[3]) * p[6]
    return p[5], p[5]


@njit(cache=True)
def build_cell_grid(
    params: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int
) -> tuple[np.ndarray, np.ndarray]:
    """Bin primitives `params (P, 9) float64` into a 2D grid of `nx * ny` cells.

    Returns `cell_start (nx*ny + 1,) int64`, `items (M,) int32` and `cell_ztop (nx*ny,) float64`:
    the primitives of cell (ix, iy) are `items[cell_start[c]:cell_start[c + 1]]`, c = iy * nx + ix,
    in increasing order; `cell_ztop[c]` is the highest top among them (-inf if none).
    """
    n_cells = nx * ny
    counts = np.zeros(n_cells + 1, np.int64)
    bounds = np.empty((params.shape[0], 4), np.int64)
    for i in range(params.shape[0]):
        ex, ey = _xy_extent(params[i])
        ix0 = max(int(np.floor((params[i, 1] - ex - x0) / cell)), 0)
        ix1 = min(int(np.floor((params[i, 1] + ex - x0) / cell)), nx - 1)
        iy0 = max(int(np.floor((params[i, 2] - ey - y0) / cell)), 0)
        iy1 = min(int(np.floor((params[i, 2] + ey - y0) / cell)), ny - 1)
        bounds[i, 0], bounds[i, 1], bounds[i, 2], bounds[i, 3] = ix0, ix1, iy0, iy1
        for iy in range(iy0, iy1 + 1):
            for ix in range(ix0, ix1 + 1):
                counts[iy * nx + ix + 1] += 1
    cell_start = np.cumsum(counts)
    fill = cell_start[:-1].copy()
    items = np.empty(cell_start[-1], np.int32)
    for i in range(params.shape[0]):
        for iy in range(bounds[i, 2], bounds[i, 3] + 1):
            for ix in range(bounds[i, 0], bounds[i, 1] + 1):
                c = iy * nx + ix
                items[fill[c]] = i
                fill[c] += 1
    cell_ztop = np.full(n_cells, -np.inf)
    for c in range(n_cells):
        for k in range(cell_start[c], cell_start[c + 1]):
            cell_ztop[c] = max(cell_ztop[c], params[items[k], 8])
    return cell_start, items, cell_ztop


# --------------------------------------------------------------------------------------------
# Ray-primitive intersection and casting
# --------------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _slab(o: float, d: float, lo: float, hi: float, tn: float, tf: float) -> tuple[float, float]:
    if abs(d) < 1e-15:
        if o < lo or o > hi:
            return 1.0, -1.0  # empty
        return tn, tf
    a = (lo - o) / d
    b = (hi - o) / d
    if a > b:
        a, b = b, a
    return max(tn, a), min(tf, b)


@njit(cache=True, inline="always")
def _hit_primitive(p: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float) -> float:
    """Entry distance of the ray into primitive `p (9,)`, or +inf (rays starting inside miss)."""
    rx = ox - p[1]
    ry = oy - p[2]
    tn, tf = _slab(oz, dz, p[7], p[8], -np.inf, np.inf)
    if tn > tf:
        return np.inf
    if p[0] == 0.0:
        c, s = p[3], p[4]
        tn, tf = _slab(c * rx + s * ry, c * dx + s * dy, -p[5], p[5], tn, tf)
        if tn > tf:
            return np.inf
        tn, tf = _slab(-s * rx + c * ry, -s * dx + c * dy, -p[6], p[6], tn, tf)
    else:
        a = dx * dx + dy * dy
        b = 2.0 * (rx * dx + ry * dy)
        cc = rx * rx + ry * ry - p[5] * p[5]
        if a < 1e-18:
            if cc > 0.0:
                return np.inf
        else:
            disc = b * b - 4.0 * a * cc
            if disc < 0.0:
                return np.inf
            sq = np.sqrt(disc)
            tn = max(tn, (-b - sq) / (2.0 * a))
            tf = min(tf, (-b + sq) / (2.0 * a))
    if tn > tf or tn <= _EPS_T:
        return np.inf
    return tn


@njit(cache=True)
def _cast_one(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, t_max: float,
    params: np.ndarray, cell_start: np.ndarray, items: np.ndarray, cell_ztop: np.ndarray,
    x0: float, y0: float, cell: float, nx: int, ny: int, z_top: float,
) -> tuple[float, int]:
    t_ground = np.inf
    if dz < 0.0 and oz > 0.0:
        t_ground = -oz / dz
    t_end = min(t_max, t_ground)
    if dz > 0.0:
        t_end = min(t_end, max((z_top - oz) / dz, 0.0))
    # Clip the ray to the grid's xy rectangle.
    ta, tb = _slab(ox, dx, x0, x0 + nx * cell, 0.0, t_end)
    ta, tb = _slab(oy, dy, y0, y0 + ny * cell, ta, tb)
    best_t = np.inf
    best = -1
    if ta <= tb:
        px = ox + ta * dx
        py = oy + ta * dy
        ix = min(max(int(np.floor((px - x0) / cell)), 0), nx - 1)
        iy = min(max(int(np.floor((py - y0) / cell)), 0), ny - 1)
        step_x = 1 if dx > 0.0 else -1
        step_y = 1 if dy > 0.0 else -1
        if dx != 0.0:
            t_next_x = (x0 + (ix + (1 if dx > 0.0 else 0)) * cell - ox) / dx
            t_dx = cell / abs(dx)
        else:
            t_next_x = np.inf
            t_dx = np.inf
        if dy != 0.0:
            t_next_y = (y0 + (iy + (1 if dy > 0.0 else 0)) * cell - oy) / dy
            t_dy = cell / abs(dy)
        else:
            t_next_y = np.inf
            t_dy = np.inf
        t_in = ta
        while True:
            c = iy * nx + ix
            t_exit = min(t_next_x, t_next_y)
            # Skip the cell when the ray passes above everything in it.
            if min(oz + t_in * dz, oz + min(t_exit, tb) * dz) <= cell_ztop[c]:
                for k in range(cell_start[c], cell_start[c + 1]):
                    j = items[k]
                    th = _hit_primitive(params[j], ox, oy, oz, dx, dy, dz)
                    if th < best_t:
                        best_t = th
                        best = j
            t_in = t_exit
            if best_t <= t_exit or t_exit > tb:
                break
            if t_next_x < t_next_y:
                ix += step_x
                t_next_x += t_dx
                if ix < 0 or ix >= nx:
                    break
            else:
                iy += step_y
                t_next_y += t_dy
                if iy < 0 or iy >= ny:
                    break
    if best >= 0 and best_t <= t_end:
        return best_t, best
    if t_ground <= t_max:
        return t_ground, -2
    return 0.0, -1


@njit(cache=True, parallel=True)
def cast_rays(
    origin: np.ndarray, dirs: np.ndarray, t_max: float,
    params: np.ndarray, cell_start: np.ndarray, items: np.ndarray, cell_ztop: np.ndarray,
    x0: float, y0: float, cell: float, nx: int, ny: int, z_top: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays `origin (3,) + t * dirs (N, 3)` (float64, global) into the world.

    Returns `t (N,) float64` (ray parameter of the first hit, in units of |dir|; 0 if none) and
    `hit (N,) int32`: primitive index, `HIT_GROUND` (-2, plane z = 0) or `HIT_NONE` (-1: sky or
    beyond `t_max`). Primitives must be binned with `build_cell_grid(params, x0, y0, cell, nx, ny)`;
    `z_top` must be >= every primitive's top.
    """
    n = dirs.shape[0]
    t_out = np.zeros(n, np.float64)
    hit_out = np.full(n, -1, np.int32)
    for i in prange(n):
        t, h = _cast_one(origin[0], origin[1], origin[2], dirs[i, 0], dirs[i, 1], dirs[i, 2], t_max,
                         params, cell_start, items, cell_ztop, x0, y0, cell, nx, ny, z_top)
        t_out[i] = t
        hit_out[i] = h
    return t_out, hit_out


# --------------------------------------------------------------------------------------------
# Surface normals
# --------------------------------------------------------------------------------------------
@njit(cache=True)
def _normal_one(p: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    rx = x - p[1]
    ry = y - p[2]
    d_top = p[8] - z
    d_bot = z - p[7]
    if p[0] == 0.0:
        c, s = p[3], p[4]
        lx = c * rx + s * ry
        ly = -s * rx + c * ry
        d_x = p[5] - abs(lx)
        d_y = p[6] - abs(ly)
        m = min(d_x, d_y, d_top, d_bot)
        if m == d_top:
            return 0.0, 0.0, 1.0
        if m == d_bot:
            return 0.0, 0.0, -1.0
        if m == d_x:
            sg = 1.0 if lx >= 0.0 else -1.0
            return sg * c, sg * s, 0.0
        sg = 1.0 if ly >= 0.0 else -1.0
        return -sg * s, sg * c, 0.0
    rr = np.sqrt(rx * rx + ry * ry)
    d_side = p[5] - rr
    m = min(d_side, d_top, d_bot)
    if m == d_top:
        return 0.0, 0.0, 1.0
    if m == d_bot:
        return 0.0, 0.0, -1.0
    if rr < 1e-12:
        return 1.0, 0.0, 0.0
    return rx / rr, ry / rr, 0.0


@njit(cache=True, parallel=True)
def hit_normals(origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, hit: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Outward unit normals `(N, 3) float32` at the hits of `cast_rays` (ground: +z; no hit: 0)."""
    n = dirs.shape[0]
    out = np.zeros((n, 3), np.float32)
    for i in prange(n):
        h = hit[i]
        if h == -2:
            out[i, 2] = 1.0
        elif h >= 0:
            x = origin[0] + t[i] * dirs[i, 0]
            y = origin[1] + t[i] * dirs[i, 1]
            z = origin[2] + t[i] * dirs[i, 2]
            a, b, c = _normal_one(params[h], x, y, z)
            out[i, 0], out[i, 1], out[i, 2] = a, b, c
    return out


# --------------------------------------------------------------------------------------------
# Shading
# --------------------------------------------------------------------------------------------
def palette_tables() -> tuple[np.ndarray, np.ndarray]:
    """`(base (18, 3) float64, variants (18, 8, 3) float64)`: class base colours and per-instance
    colour variants (RGB 0-255). Realistic-looking colours, distinct per class."""
    base = np.array([
        [90, 90, 90], [215, 95, 35], [150, 45, 130], [230, 185, 35], [0, 0, 0], [200, 200, 40],
        [235, 110, 20], [0, 0, 0], [250, 95, 0], [120, 70, 30], [0, 0, 0], [72, 72, 78],
        [150, 138, 115], [188, 182, 172], [92, 128, 52], [0, 0, 0], [38, 112, 40], [0, 0, 0],
    ], np.float64)
    variants = np.repeat(base[:, None, :], 8, axis=1)
    variants[4] = [[175, 28, 30], [222, 222, 226], [28, 28, 34], [150, 154, 160], [38, 68, 160], [115, 20, 32],
                   [200, 198, 185], [58, 88, 62]]  # cars
    variants[7] = [[200, 40, 40], [40, 80, 170], [230, 230, 230], [60, 140, 70], [240, 200, 40], [120, 60, 150],
                   [30, 30, 30], [230, 120, 160]]  # pedestrian shirts
    variants[10] = [[235, 235, 235], [200, 40, 35], [40, 80, 150], [230, 230, 220], [240, 240, 240],
                    [60, 120, 60], [220, 220, 225], [170, 170, 175]]  # trucks
    variants[15] = [[190, 170, 150], [160, 150, 140], [205, 195, 172], [140, 118, 108], [176, 176, 182],
                    [212, 202, 182], [122, 112, 102], [186, 160, 130]]  # buildings
    variants[16] = variants[16] * np.linspace(0.8, 1.2, 8)[:, None]
    return base, variants


@njit(cache=True, inline="always")
def _hash01(a: int, b: int, c: int) -> float:
    h = ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) % 1000003
    return h / 1000003.0


@njit(cache=True, inline="always")
def _frac(x: float) -> float:
    return x - np.floor(x)


@njit(cache=True)
def _shade_one(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, t: float, h: int,
    nx_: float, ny_: float, nz_: float, cls_: int, style: int, gcode: int,
    variants: np.ndarray, sun: np.ndarray,
) -> tuple[float, float, float]:
    dn = np.sqrt(dx * dx + dy * dy + dz * dz)
    if h == -1:  # sky: horizon haze to zenith blue
        a = min(max(dz / dn * 2.5, 0.0), 1.0)
        return 205.0 + a * (100.0 - 205.0), 215.0 + a * (150.0 - 215.0), 230.0 + a * (215.0 - 230.0)
    x = ox + t * dx
    y = oy + t * dy
    z = oz + t * dz
    v = style & 7
    r, g, b = variants[cls_, v, 0], variants[cls_, v, 1], variants[cls_, v, 2]
    tex = 1.0
    hh = -ny_ * x + nx_ * y  # horizontal coordinate along a vertical face
    if h == -2:
        mark = gcode >> 5
        if cls_ == 11:
            tex = 0.92 + 0.16 * _hash01(int(np.floor(x * 10.0)), int(np.floor(y * 10.0)), 7)
            if mark == 1:
                r, g, b = 215.0, 185.0, 45.0
            elif mark == 2:
                r, g, b = 225.0, 225.0, 225.0
        elif cls_ == 13:
            joint = _frac(x / 0.8) < 0.06 or _frac(y / 0.8) < 0.06
            tex = 0.7 if joint else 0.95 + 0.1 * _hash01(int(np.floor(x / 0.8)), int(np.floor(y / 0.8)), 3)
        elif cls_ == 14:
            tex = 0.7 + 0.5 * _hash01(int(np.floor(x * 3.0)), int(np.floor(y * 3.0)), 11)
        else:
            tex = 0.85 + 0.3 * _hash01(int(np.floor(x * 5.0)), int(np.floor(y * 5.0)), 5)
    elif (style & 16) != 0 and nz_ < 0.5:  # glass (car cabin sides, truck cab)
        r, g, b = 45.0, 55.0, 70.0
    elif cls_ == 15:
        if (style & 128) != 0:
            r, g, b = 112.0, 112.0, 118.0
        elif (style & 64) != 0:
            r, g, b = 158.0, 156.0, 148.0
            tex = 0.9 + 0.15 * _hash01(int(np.floor(hh * 2.0)), int(np.floor(z * 2.0)), 13)
        elif nz_ < 0.5 and z > 1.2 and _frac(hh / 3.0) > 0.3 and _frac(hh / 3.0) < 0.8 \
                and _frac(z / 3.5) > 0.35 and _frac(z / 3.5) < 0.8:
            w = _hash01(int(np.floor(hh / 3.0)), int(np.floor(z / 3.5)), 17)
            r, g, b = 50.0 + 40.0 * w, 62.0 + 40.0 * w, 82.0 + 40.0 * w
    elif cls_ == 16:
        if (style & 32) != 0:
            r, g, b = 92.0, 66.0, 42.0
        else:
            tex = 0.6 + 0.7 * _hash01(int(np.floor(x * 4.0)), int(np.floor(y * 4.0)), int(np.floor(z * 4.0)))
    elif cls_ == 4 or cls_ == 3 or cls_ == 10:
        if z < 0.35 and nz_ < 0.5:  # wheels and sills
            r, g, b = 25.0, 25.0, 25.0
        elif cls_ == 3 and z > 1.3 and z < 2.6 and nz_ < 0.5:  # bus window band
            r, g, b = 45.0, 55.0, 70.0
    elif cls_ == 7:
        if z < 0.9:
            r, g, b = 40.0, 42.0, 62.0
        elif z > 1.4:
            r, g, b = 205.0, 165.0, 135.0
    elif cls_ == 1:
        if _frac((hh + z) / 0.5) < 0.5:
            r, g, b = 235.0, 235.0, 235.0
    elif cls_ == 8:
        if z > 0.4 and z < 0.55:
            r, g, b = 240.0, 240.0, 240.0
    elif cls_ == 2 or cls_ == 6:
        if z < 0.7:
            r, g, b = 30.0, 30.0, 30.0
    lam = max(nx_ * sun[0] + ny_ * sun[1] + nz_ * sun[2], 0.0)
    k = tex * (0.55 + 0.45 * lam)
    fog = np.exp(-t * dn / 250.0)
    return (r * k * fog + 205.0 * (1.0 - fog), g * k * fog + 215.0 * (1.0 - fog), b * k * fog + 230.0 * (1.0 - fog))


# --------------------------------------------------------------------------------------------
# Fused camera renderer
# --------------------------------------------------------------------------------------------
@njit(cache=True, parallel=True)
def render_camera_kernel(
    K_inv: np.ndarray, R_global_from_cam: np.ndarray, origin: np.ndarray, width: int, height: int, t_max: float,
    params: np.ndarray, cell_start: np.ndarray, items: np.ndarray, cell_ztop: np.ndarray,
    x0: float, y0: float, cell: float, nx: int, ny: int, z_top: float,
    prim_cls: np.ndarray, prim_style: np.ndarray, gcodes: np.ndarray, gx0: float, gy0: float, gcell: float,
    variants: np.ndarray, sun: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one pinhole camera: rays through pixel centres (integer pixel coordinates), camera-frame
    direction `K_inv @ (u, v, 1)` (z = 1, so the ray parameter is the depth), rotated to global.

    Returns `rgb (H, W, 3) uint8`, `depth (H, W) float32` (camera z, 0 where nothing is hit) and
    `classes (H, W) uint8`, the Occ3D class of the surface each pixel sees (`SKY_CLASS` where none).
    Same per-pixel maths as `cast_rays` + `hit_normals` + shading, without the large temporaries.
    """
    rgb = np.zeros((height, width, 3), np.uint8)
    depth = np.zeros((height, width), np.float32)
    classes = np.full((height, width), SKY_CLASS, np.uint8)
    gny, gnx = gcodes.shape
    for v in prange(height):
        for u in range(width):
            cx = K_inv[0, 0] * u + K_inv[0, 1] * v + K_inv[0, 2]
            cy = K_inv[1, 0] * u + K_inv[1, 1] * v + K_inv[1, 2]
            cz = K_inv[2, 0] * u + K_inv[2, 1] * v + K_inv[2, 2]
            dx = R_global_from_cam[0, 0] * cx + R_global_from_cam[0, 1] * cy + R_global_from_cam[0, 2] * cz
            dy = R_global_from_cam[1, 0] * cx + R_global_from_cam[1, 1] * cy + R_global_from_cam[1, 2] * cz
            dz = R_global_from_cam[2, 0] * cx + R_global_from_cam[2, 1] * cy + R_global_from_cam[2, 2] * cz
            t, h = _cast_one(origin[0], origin[1], origin[2], dx, dy, dz, t_max, params, cell_start, items,
                             cell_ztop, x0, y0, cell, nx, ny, z_top)
            nx_, ny_, nz_ = 0.0, 0.0, 0.0
            c = 0
            st = 0
            gc = 0
            if h >= 0:
                nx_, ny_, nz_ = _normal_one(params[h], origin[0] + t * dx, origin[1] + t * dy, origin[2] + t * dz)
                c = prim_cls[h]
                st = prim_style[h]
                depth[v, u] = t
                classes[v, u] = c
            elif h == -2:
                nz_ = 1.0
                ix = int(np.floor((origin[0] + t * dx - gx0) / gcell))
                iy = int(np.floor((origin[1] + t * dy - gy0) / gcell))
                gc = 14
                if 0 <= ix < gnx and 0 <= iy < gny:
                    gc = gcodes[iy, ix]
                c = gc & 31
                depth[v, u] = t
                classes[v, u] = c
            # Normals are stored as float32 by `hit_normals`; round the same way for identical shading.
            r, g, b = _shade_one(origin[0], origin[1], origin[2], dx, dy, dz, t, h, np.float32(nx_),
                                 np.float32(ny_), np.float32(nz_), c, st, gc, variants, sun)
            rgb[v, u, 0] = min(max(int(r + 0.5), 0), 255)
            rgb[v, u, 1] = min(max(int(g + 0.5), 0), 255)
            rgb[v, u, 2] = min(max(int(b + 0.5), 0), 255)
    return rgb, depth, classes
