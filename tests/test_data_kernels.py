"""Numba kernels of the loader vs their numpy twins, on random inputs."""

from __future__ import annotations

import numpy as np
import pytest
from reference.sensors_depth_targets import depth_target_reference, min_pool_depth_reference, rasterise_depth_reference
from reference.sensors_image_ops import normalise_chw_reference

from occdata.sensors.depth_targets import depth_target, min_pool_depth, rasterise_depth
from occdata.sensors.image_ops import normalise_chw, normalise_lut


def _random_A(rng: np.random.Generator) -> np.ndarray:
    a = np.radians(rng.uniform(-5.4, 5.4))
    s = rng.uniform(0.38, 0.55)
    A = np.array([[s * np.cos(a), -s * np.sin(a), rng.uniform(-60, 10)],
                  [s * np.sin(a), s * np.cos(a), rng.uniform(-160, -100)], [0, 0, 1]])
    if rng.random() < 0.5:
        A = np.array([[-1.0, 0, 703], [0, 1, 0], [0, 0, 1]]) @ A
    return A


@pytest.mark.parametrize("seed", range(5))
def test_depth_kernels_match_numpy_twins(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = 5000
    # Points on a coarse lattice so that several land on the same pixel (the nearest must win).
    uvd = np.stack([rng.integers(0, 400, m) * 4.0, rng.integers(0, 225, m) * 4.0,
                    rng.uniform(0.1, 60, m)], axis=1).astype(np.float32)
    A = _random_A(rng)
    raster = rasterise_depth(uvd, A, 256, 704, 1.0, 45.0)
    np.testing.assert_array_equal(raster, rasterise_depth_reference(uvd, A, 256, 704, 1.0, 45.0))
    assert (raster > 0).sum() > 1000 and raster.max() < 45.0 and raster[raster > 0].min() >= 1.0
    pooled = min_pool_depth(raster, 16)
    np.testing.assert_array_equal(pooled, min_pool_depth_reference(raster, 16))
    fused = depth_target(uvd, A, 256, 704, 16, 1.0, 45.0)
    np.testing.assert_array_equal(fused, pooled)
    np.testing.assert_array_equal(fused, depth_target_reference(uvd, A, 256, 704, 16, 1.0, 45.0))


def test_rasterise_keeps_nearest_and_rounds_half_up() -> None:
    uvd = np.array([[10.4, 5.5, 9.0], [10.0, 6.0, 3.0], [10.2, 5.6, 7.0], [-0.6, 0, 2.0], [0, 0, 50.0]], np.float32)
    out = rasterise_depth(uvd, np.eye(3), 32, 32, 1.0, 45.0)
    assert out[6, 10] == 3.0  # three points round to (u=10, v=6): nearest kept
    assert out[0, 0] == 0  # (-0.6 -> -1) outside, 50 m out of range
    assert (out > 0).sum() == 1


def test_normalise_matches_numpy_twin() -> None:
    img = np.random.default_rng(0).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    out = np.empty((3, 37, 53), np.float32)
    normalise_chw(img, normalise_lut(), out)
    np.testing.assert_allclose(out, normalise_chw_reference(img), rtol=0, atol=1e-6)
