"""Every numba kernel of occdata.synth agrees with its numpy twin on random inputs."""

from __future__ import annotations

import numpy as np
import pytest
from reference.synth_labels import voxelize_primitives_reference
from reference.synth_render import (
    build_cell_grid_reference,
    cast_rays_reference,
    hit_normals_reference,
    render_camera_reference,
)

from occdata.synth import render
from occdata.synth.labels import CLASS_PRIORITY, voxelize_primitives


def _random_prims(rng: np.random.Generator, n: int, extent: float = 30.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    kind = rng.integers(0, 2, n).astype(np.float64)
    yaw = rng.uniform(-np.pi, np.pi, n)
    z0 = rng.uniform(0.0, 1.5, n) * (rng.random(n) < 0.5)
    params = np.stack([kind, rng.uniform(-extent, extent, n), rng.uniform(-extent, extent, n), np.cos(yaw),
                       np.sin(yaw), rng.uniform(0.1, 4.0, n), rng.uniform(0.1, 4.0, n), z0,
                       z0 + rng.uniform(0.3, 8.0, n)], axis=1)
    cls = rng.choice([1, 2, 3, 4, 6, 7, 8, 10, 15, 16], n).astype(np.int32)
    style = rng.integers(0, 256, n).astype(np.int32)
    return params, cls, style


def _grid(params: np.ndarray, cell: float, extent: float = 40.0):
    x0 = y0 = -extent
    n = int(np.ceil(2 * extent / cell))
    return (x0, y0, cell, n, n, *render.build_cell_grid(params, x0, y0, cell, n, n))


@pytest.mark.parametrize("seed", [0, 1])
def test_build_cell_grid_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    params, _, _ = _random_prims(rng, 40)
    for got, ref in zip(render.build_cell_grid(params, -40.0, -40.0, 7.0, 12, 11),
                        build_cell_grid_reference(params, -40.0, -40.0, 7.0, 12, 11), strict=True):
        np.testing.assert_array_equal(got, ref)


def _random_rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    origin = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(0.5, 3.0)])
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] = dirs[:, 2] * 0.4
    dirs[: n // 10, :2] = 0.0  # some vertical rays
    dirs[n // 10: n // 5, 2] = 0.0  # some horizontal rays
    dirs[: n // 20, 2] = -1.0
    return origin, dirs * rng.uniform(0.5, 2.0, (n, 1))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cast_rays_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    params, _, _ = _random_prims(rng, 60)
    x0, y0, cell, nx, ny, cs, items, ztop = _grid(params, 4.0)
    origin, dirs = _random_rays(rng, 3000)
    keep = np.array([render._hit_primitive(p, *origin, 0.0, 0.0, 1.0) for p in params]) < np.inf
    # Rays starting inside a primitive are not meaningful; move such primitives away from the origin.
    inside = [(abs(p[1] - origin[0]) < 5 and abs(p[2] - origin[1]) < 5) for p in params]
    params[np.array(inside) | keep, 1] += 20.0
    x0, y0, cell, nx, ny, cs, items, ztop = _grid(params, 4.0)
    z_top = params[:, 8].max() + 0.01
    t, hit = render.cast_rays(origin, dirs, 60.0, params, cs, items, ztop, x0, y0, cell, nx, ny, z_top)
    t_ref, hit_ref = cast_rays_reference(origin, dirs, 60.0, params)
    assert (hit >= 0).sum() > 200 and (hit == render.HIT_GROUND).sum() > 100 and (hit == render.HIT_NONE).sum() > 50
    np.testing.assert_array_equal(hit, hit_ref)
    np.testing.assert_allclose(t, t_ref, rtol=1e-9, atol=1e-9)
    n = render.hit_normals(origin, dirs, t, hit, params)
    np.testing.assert_allclose(n, hit_normals_reference(origin, dirs, t, hit, params), atol=1e-6)
    assert np.allclose(np.linalg.norm(n[hit != render.HIT_NONE], axis=1), 1.0, atol=1e-5)
    # Normals face the incoming ray.
    assert (np.einsum("ij,ij->i", n[hit >= 0], dirs[hit >= 0]) < 1e-6).all()


def _ground(rng: np.random.Generator) -> tuple[np.ndarray, float, float, float]:
    codes = rng.choice([11, 12, 13, 14], (60, 70)).astype(np.uint8)
    codes[rng.random(codes.shape) < 0.1] |= 1 << 5
    codes[rng.random(codes.shape) < 0.1] |= 2 << 5
    return codes, -7.0, -6.0, 0.2


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_render_camera_kernel_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    params, cls, style = _random_prims(rng, 30, extent=12.0)
    params[:, 1] += 22.0  # everything ahead of the camera, low enough to leave sky
    params[:, 8] = np.minimum(params[:, 8], params[:, 7] + 2.5)
    x0, y0, cell, nx, ny, cs, items, ztop = _grid(params, 4.0)
    codes, gx0, gy0, gcell = _ground(rng)
    _, variants = render.palette_tables()
    K = np.array([[40.0, 0.0, 31.5], [0.0, 40.0, 17.5], [0.0, 0.0, 1.0]])
    # Camera looking along +x (camera z -> global x, camera x -> -global y, camera y -> -global z).
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    origin = np.array([0.0, 0.0, 1.5])
    rgb, depth, classes = render.render_camera_kernel(np.linalg.inv(K), R, origin, 64, 36, 80.0, params, cs, items,
                                                      ztop, x0, y0, cell, nx, ny, 30.0, cls, style, codes, gx0, gy0,
                                                      gcell, variants, render.SUN_DIR)
    rgb_ref, depth_ref, classes_ref = render_camera_reference(K, R, origin, 64, 36, 80.0, params, cls, style, codes,
                                                              gx0, gy0, gcell, variants, render.SUN_DIR)
    np.testing.assert_allclose(depth, depth_ref, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(classes, classes_ref)
    assert ((classes == render.SKY_CLASS) == (depth == 0)).all() and len(np.unique(classes)) >= 3
    assert np.abs(rgb.astype(int) - rgb_ref.astype(int)).max() <= 1
    assert (depth == 0).any() and (depth > 0).any()
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 50  # textured, shaded, not flat colours


@pytest.mark.parametrize("seed", [0, 1])
def test_voxelize_matches_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    params, cls, _ = _random_prims(rng, 25, extent=4.0)
    params[:, 5:7] *= 0.5
    sem = np.full((24, 22, 10), 17, np.uint8)
    sem[:, :, 2] = rng.choice([11, 13, 14], (24, 22))
    lower = np.array([-4.8, -4.4, -1.0])
    got = voxelize_primitives(sem, params, cls, CLASS_PRIORITY, lower, 0.4)
    ref = voxelize_primitives_reference(sem, params, cls, CLASS_PRIORITY, lower, 0.4)
    np.testing.assert_array_equal(got, ref)
    assert (got != sem).sum() > 100
    # Every surface point of every primitive lies in an occupied voxel (checked on sampled points).
    for p in params:
        for _ in range(50):
            z = rng.uniform(p[7], p[8])
            if p[0] == 0.0:
                lx, ly = rng.uniform(-p[5], p[5]), rng.uniform(-p[6], p[6])
                x, y = p[1] + p[3] * lx - p[4] * ly, p[2] + p[4] * lx + p[3] * ly
            else:
                a, r = rng.uniform(0, 2 * np.pi), p[5] * np.sqrt(rng.random())
                x, y = p[1] + r * np.cos(a), p[2] + r * np.sin(a)
            idx = np.floor((np.array([x, y, z]) - lower) / 0.4).astype(int)
            if ((idx >= 0) & (idx < got.shape)).all():
                assert got[tuple(idx)] != 17
