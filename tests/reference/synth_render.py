"""Test oracles for `occdata.synth.render`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.synth.render import _EPS_T, HIT_NONE

__all__ = ["build_cell_grid_reference", "cast_rays_reference", "hit_normals_reference", "shade_reference",
           "camera_rays_reference", "render_camera_reference"]


def build_cell_grid_reference(
    params: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int
) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin of `build_cell_grid` (same output)."""
    is_box = params[:, 0] == 0.0
    ex = np.where(is_box, np.abs(params[:, 3]) * params[:, 5] + np.abs(params[:, 4]) * params[:, 6], params[:, 5])
    ey = np.where(is_box, np.abs(params[:, 4]) * params[:, 5] + np.abs(params[:, 3]) * params[:, 6], params[:, 5])
    ix0 = np.maximum(np.floor((params[:, 1] - ex - x0) / cell), 0).astype(np.int64)
    ix1 = np.minimum(np.floor((params[:, 1] + ex - x0) / cell), nx - 1).astype(np.int64)
    iy0 = np.maximum(np.floor((params[:, 2] - ey - y0) / cell), 0).astype(np.int64)
    iy1 = np.minimum(np.floor((params[:, 2] + ey - y0) / cell), ny - 1).astype(np.int64)
    gy, gx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    per_cell: list[np.ndarray] = []
    for c_y, c_x in zip(gy.ravel(), gx.ravel(), strict=True):
        sel = (ix0 <= c_x) & (c_x <= ix1) & (iy0 <= c_y) & (c_y <= iy1)
        per_cell.append(np.flatnonzero(sel).astype(np.int32))
    cell_start = np.concatenate([[0], np.cumsum([len(p) for p in per_cell])]).astype(np.int64)
    items = np.concatenate(per_cell).astype(np.int32) if per_cell else np.zeros(0, np.int32)
    cell_ztop = np.array([params[p, 8].max() if len(p) else -np.inf for p in per_cell], np.float64)
    return cell_start, items, cell_ztop


def cast_rays_reference(
    origin: np.ndarray, dirs: np.ndarray, t_max: float, params: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Numpy twin of `cast_rays`: brute force over all primitives (no grid), same outputs."""
    o = np.asarray(origin, np.float64)
    d = np.asarray(dirs, np.float64)
    n = len(d)
    best_t = np.full(n, np.inf)
    best = np.full(n, -1, np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        for j, p in enumerate(params):
            tn = np.full(n, -np.inf)
            tf = np.full(n, np.inf)

            def slab(o1: np.ndarray | float, d1: np.ndarray, lo: float, hi: float) -> None:
                nonlocal tn, tf
                par = np.abs(d1) < 1e-15
                a = (lo - o1) / d1
                b = (hi - o1) / d1
                lo_t = np.where(par, -np.inf, np.minimum(a, b))
                hi_t = np.where(par, np.inf, np.maximum(a, b))
                outside = par & ((o1 < lo) | (o1 > hi))
                tn = np.where(outside, np.inf, np.maximum(tn, lo_t))
                tf = np.where(outside, -np.inf, np.minimum(tf, hi_t))

            rx, ry = o[0] - p[1], o[1] - p[2]
            slab(np.full(n, o[2]), d[:, 2], p[7], p[8])
            if p[0] == 0.0:
                c, s = p[3], p[4]
                slab(np.full(n, c * rx + s * ry), c * d[:, 0] + s * d[:, 1], -p[5], p[5])
                slab(np.full(n, -s * rx + c * ry), -s * d[:, 0] + c * d[:, 1], -p[6], p[6])
            else:
                a = d[:, 0] ** 2 + d[:, 1] ** 2
                b = 2.0 * (rx * d[:, 0] + ry * d[:, 1])
                cc = rx * rx + ry * ry - p[5] ** 2
                disc = b * b - 4.0 * a * cc
                vert = a < 1e-18
                sq = np.sqrt(np.maximum(disc, 0.0))
                miss = np.where(vert, cc > 0.0, disc < 0.0)
                tn = np.where(vert, tn, np.maximum(tn, (-b - sq) / (2.0 * a)))
                tf = np.where(vert, tf, np.minimum(tf, (-b + sq) / (2.0 * a)))
                tn = np.where(miss, np.inf, tn)
            ok = (tn <= tf) & (tn > _EPS_T) & (tn < best_t)
            best_t = np.where(ok, tn, best_t)
            best = np.where(ok, j, best)
        t_ground = np.where((d[:, 2] < 0) & (o[2] > 0), -o[2] / d[:, 2], np.inf)
    t_end = np.minimum(t_max, t_ground)
    prim_ok = (best >= 0) & (best_t <= t_end)
    ground_ok = ~prim_ok & (t_ground <= t_max)
    t_out = np.where(prim_ok, best_t, np.where(ground_ok, t_ground, 0.0))
    hit = np.where(prim_ok, best, np.where(ground_ok, -2, -1)).astype(np.int32)
    return t_out, hit


def hit_normals_reference(
    origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, hit: np.ndarray, params: np.ndarray
) -> np.ndarray:
    """Numpy twin of `hit_normals`."""
    n = len(dirs)
    out = np.zeros((n, 3), np.float64)
    out[hit == -2, 2] = 1.0
    sel = hit >= 0
    if sel.any():
        p = params[hit[sel]]
        pts = origin + t[sel, None] * dirs[sel]
        rx, ry, z = pts[:, 0] - p[:, 1], pts[:, 1] - p[:, 2], pts[:, 2]
        d_top, d_bot = p[:, 8] - z, z - p[:, 7]
        c, s = p[:, 3], p[:, 4]
        lx, ly = c * rx + s * ry, -s * rx + c * ry
        is_box = p[:, 0] == 0.0
        rr = np.sqrt(rx * rx + ry * ry)
        d_x = np.where(is_box, p[:, 5] - np.abs(lx), p[:, 5] - rr)
        d_y = np.where(is_box, p[:, 6] - np.abs(ly), np.inf)
        m = np.minimum(np.minimum(d_x, d_y), np.minimum(d_top, d_bot))
        sgx = np.where(lx >= 0, 1.0, -1.0)
        sgy = np.where(ly >= 0, 1.0, -1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            side_x = np.where(is_box[:, None], np.stack([sgx * c, sgx * s, 0 * c], 1),
                              np.where((rr < 1e-12)[:, None], [[1.0, 0.0, 0.0]],
                                       np.stack([rx / rr, ry / rr, 0 * rr], 1)))
        side_y = np.stack([-sgy * s, sgy * c, 0 * c], 1)
        nrm = np.where((m == d_y)[:, None], side_y, side_x)
        nrm = np.where((m == d_bot)[:, None], [[0.0, 0.0, -1.0]], nrm)
        nrm = np.where((m == d_top)[:, None], [[0.0, 0.0, 1.0]], nrm)
        out[sel] = nrm
    return out.astype(np.float32)


def shade_reference(
    origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, hit: np.ndarray, normals: np.ndarray,
    prim_cls: np.ndarray, prim_style: np.ndarray, gcodes: np.ndarray, gx0: float, gy0: float, gcell: float,
    variants: np.ndarray, sun: np.ndarray,
) -> np.ndarray:
    """Numpy twin of the shading in `render_camera_kernel` (`_shade_one`), vectorised over pixels:
    RGB `(N, 3) uint8`; may differ by 1 in rounding."""
    d = np.asarray(dirs, np.float64)
    n = len(d)
    dn = np.linalg.norm(d, axis=1)
    p = origin + t[:, None] * d
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    nrm = normals.astype(np.float64)
    nx_, ny_, nz_ = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    ix = np.floor((x - gx0) / gcell).astype(np.int64)
    iy = np.floor((y - gy0) / gcell).astype(np.int64)
    gny, gnx = gcodes.shape
    inside = (ix >= 0) & (ix < gnx) & (iy >= 0) & (iy < gny)
    gc = np.where(hit == -2, 14, 0).astype(np.int64)
    sel = inside & (hit == -2)
    gc[sel] = gcodes[iy[sel], ix[sel]]
    hp = np.maximum(hit, 0)
    cls_ = np.where(hit >= 0, prim_cls[hp], np.where(hit == -2, gc & 31, 0)).astype(np.int64)
    style = np.where(hit >= 0, prim_style[hp], 0).astype(np.int64)
    rgb = variants[cls_, style & 7].copy()
    tex = np.ones(n)
    hh = -ny_ * x + nx_ * y

    def h01(a: np.ndarray, b: np.ndarray, c: np.ndarray | int) -> np.ndarray:
        a = a.astype(np.int64)
        b = b.astype(np.int64)
        c = np.asarray(c).astype(np.int64)
        return ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) % 1000003 / 1000003.0

    def frac(v: np.ndarray) -> np.ndarray:
        return v - np.floor(v)

    def setc(mask: np.ndarray, col: tuple[float, float, float] | np.ndarray) -> None:
        rgb[mask] = np.broadcast_to(np.asarray(col, np.float64), rgb.shape)[mask]

    fl = np.floor
    ground = hit == -2
    mark = gc >> 5
    road = ground & (cls_ == 11)
    tex = np.where(road, 0.92 + 0.16 * h01(fl(x * 10), fl(y * 10), 7), tex)
    setc(road & (mark == 1), (215.0, 185.0, 45.0))
    setc(road & (mark == 2), (225.0, 225.0, 225.0))
    side = ground & (cls_ == 13)
    joint = (frac(x / 0.8) < 0.06) | (frac(y / 0.8) < 0.06)
    tex = np.where(side, np.where(joint, 0.7, 0.95 + 0.1 * h01(fl(x / 0.8), fl(y / 0.8), 3)), tex)
    terr = ground & (cls_ == 14)
    tex = np.where(terr, 0.7 + 0.5 * h01(fl(x * 3), fl(y * 3), 11), tex)
    oth = ground & ~(road | side | terr)
    tex = np.where(oth, 0.85 + 0.3 * h01(fl(x * 5), fl(y * 5), 5), tex)

    obj = hit >= 0
    vertical = nz_ < 0.5
    glass = obj & ((style & 16) != 0) & vertical
    setc(glass, (45.0, 55.0, 70.0))
    rest = obj & ~glass
    mm = rest & (cls_ == 15)
    pole = mm & ((style & 128) != 0)
    setc(pole, (112.0, 112.0, 118.0))
    wall = mm & ~pole & ((style & 64) != 0)
    setc(wall, (158.0, 156.0, 148.0))
    tex = np.where(wall, 0.9 + 0.15 * h01(fl(hh * 2), fl(z * 2), 13), tex)
    fh, fz = frac(hh / 3.0), frac(z / 3.5)
    win = mm & ~pole & ~wall & vertical & (z > 1.2) & (fh > 0.3) & (fh < 0.8) & (fz > 0.35) & (fz < 0.8)
    w = h01(fl(hh / 3.0), fl(z / 3.5), 17)
    setc(win, np.stack([50 + 40 * w, 62 + 40 * w, 82 + 40 * w], 1))
    veg = rest & (cls_ == 16)
    trunk = veg & ((style & 32) != 0)
    setc(trunk, (92.0, 66.0, 42.0))
    tex = np.where(veg & ~trunk, 0.6 + 0.7 * h01(fl(x * 4), fl(y * 4), fl(z * 4)), tex)
    veh = rest & ((cls_ == 4) | (cls_ == 3) | (cls_ == 10))
    wheels = veh & (z < 0.35) & vertical
    setc(wheels, (25.0, 25.0, 25.0))
    setc(veh & ~wheels & (cls_ == 3) & (z > 1.3) & (z < 2.6) & vertical, (45.0, 55.0, 70.0))
    ped = rest & (cls_ == 7)
    setc(ped & (z < 0.9), (40.0, 42.0, 62.0))
    setc(ped & (z > 1.4), (205.0, 165.0, 135.0))
    setc(rest & (cls_ == 1) & (frac((hh + z) / 0.5) < 0.5), (235.0, 235.0, 235.0))
    setc(rest & (cls_ == 8) & (z > 0.4) & (z < 0.55), (240.0, 240.0, 240.0))
    setc(rest & ((cls_ == 2) | (cls_ == 6)) & (z < 0.7), (30.0, 30.0, 30.0))

    lam = np.maximum(nx_ * sun[0] + ny_ * sun[1] + nz_ * sun[2], 0.0)
    k = tex * (0.55 + 0.45 * lam)
    fog = np.exp(-t * dn / 250.0)
    horizon = np.array([205.0, 215.0, 230.0])
    col = rgb * (k * fog)[:, None] + horizon * (1 - fog)[:, None]
    a = np.clip(d[:, 2] / dn * 2.5, 0.0, 1.0)
    sky = horizon + a[:, None] * (np.array([100.0, 150.0, 215.0]) - horizon)
    col = np.where((hit == -1)[:, None], sky, col)
    return np.clip(np.floor(col + 0.5), 0, 255).astype(np.uint8)


def camera_rays_reference(K: np.ndarray, R_global_from_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """Global ray directions `(H*W, 3) float64` through pixel centres (row-major), camera z = 1."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    return pix @ np.linalg.inv(K).T @ R_global_from_cam.T


def render_camera_reference(
    K: np.ndarray, R_global_from_cam: np.ndarray, origin: np.ndarray, width: int, height: int, t_max: float,
    params: np.ndarray, prim_cls: np.ndarray, prim_style: np.ndarray, gcodes: np.ndarray, gx0: float, gy0: float,
    gcell: float, variants: np.ndarray, sun: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy twin of `render_camera_kernel`: brute-force casting + numpy normals and shading; the
    class image from the hit primitive's class or the ground raster's (terrain outside it), 255 for sky."""
    dirs = camera_rays_reference(K, R_global_from_cam, width, height)
    t, hit = cast_rays_reference(origin, dirs, t_max, params)
    nrm = hit_normals_reference(origin, dirs, t, hit, params)
    rgb = shade_reference(origin, dirs, t, hit, nrm, prim_cls, prim_style, gcodes, gx0, gy0, gcell, variants, sun)
    depth = np.where(hit == HIT_NONE, 0.0, t).astype(np.float32)
    p = origin + t[:, None] * dirs
    ix, iy = np.floor((p[:, 0] - gx0) / gcell).astype(np.int64), np.floor((p[:, 1] - gy0) / gcell).astype(np.int64)
    inside = (ix >= 0) & (ix < gcodes.shape[1]) & (iy >= 0) & (iy < gcodes.shape[0])
    ground = np.where(inside, gcodes[np.clip(iy, 0, gcodes.shape[0] - 1), np.clip(ix, 0, gcodes.shape[1] - 1)] & 31, 14)
    classes = np.where(hit >= 0, prim_cls[np.maximum(hit, 0)], np.where(hit == -2, ground, 255)).astype(np.uint8)
    return rgb.reshape(height, width, 3), depth.reshape(height, width), classes.reshape(height, width)
