"""Test oracles for `occdata.visibility.masks`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.visibility.masks import MAX_OCCLUDERS, _camera_mask
from reference.segments import segment_hits_boxes

__all__ = ["clearance_map_reference", "count_occluders_reference", "camera_mask_reference", "lidar_ray_mask_reference"]


def clearance_map_reference(occluders: np.ndarray, max_radius: int) -> np.ndarray:
    """Numpy twin of `clearance_map`: grow the occluders by the 3x3x3 cube until `max_radius`."""
    grown = np.asarray(occluders) != 0
    out = np.full(grown.shape, max_radius, np.uint8)
    out[grown] = 0
    for r in range(1, max_radius):
        pad = np.pad(grown, 1)
        nxt = np.zeros_like(grown)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                for dk in (-1, 0, 1):
                    nxt |= pad[1 + di:pad.shape[0] - 1 + di, 1 + dj:pad.shape[1] - 1 + dj, 1 + dk:pad.shape[2] - 1 + dk]
        out[nxt & ~grown] = r
        grown = nxt
    return out


def count_occluders_reference(
    occluders: np.ndarray, clearance: np.ndarray, targets: np.ndarray, T_cam_from_grid: np.ndarray, K: np.ndarray,
    width: int, height: int, lower: np.ndarray, voxel_size: float, cap: int,
) -> np.ndarray:
    """Numpy twin of `count_occluders`: per target, a segment-vs-box test against every occluder voxel
    (`clearance` is not needed and ignored)."""
    targets = np.asarray(targets, np.int64).reshape(-1, 3)
    centres = lower + (targets + 0.5) * voxel_size
    R, t = T_cam_from_grid[:3, :3], T_cam_from_grid[:3, 3]
    pc = centres @ R.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (K[0, 0] * pc[:, 0] + K[0, 1] * pc[:, 1]) / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
    inside = (pc[:, 2] > 0) & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    cam = -(R.T @ t)
    occ_idx = np.argwhere(occluders != 0)
    lo = lower + occ_idx * voxel_size
    hi = lo + voxel_size
    out = np.full(len(targets), -1, np.int64)
    for n in np.flatnonzero(inside):
        others = ~(occ_idx == targets[n]).all(axis=1)
        hits = int(segment_hits_boxes(cam, centres[n], lo[others], hi[others]).sum())
        out[n] = min(hits, cap + 1)
    return out


def camera_mask_reference(
    semantics: np.ndarray, mask_lidar: np.ndarray, K: np.ndarray, T_cam_from_grid: np.ndarray,
    image_size: np.ndarray, lower: np.ndarray, voxel_size: float, max_occluders: int = MAX_OCCLUDERS,
) -> np.ndarray:
    """Numpy twin of `camera_mask`: every observed object voxel tested with `count_occluders_reference`."""
    return _camera_mask(semantics, mask_lidar, K, T_cam_from_grid, image_size, lower, voxel_size, max_occluders,
                        count_occluders_reference, prefilter=False)


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
        out |= segment_hits_boxes(np.asarray(a, np.float64), np.asarray(b, np.float64), lo, hi).astype(np.uint8)
    return out.reshape(tuple(shape))
