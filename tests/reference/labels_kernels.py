"""Test oracles for `occdata.labels.kernels`: plain numpy twins of its kernels, which the tests compare the kernels
against (moved out of the product module; nothing in occdata uses them)."""

from __future__ import annotations

import numpy as np

from occdata.geometry import points_in_box
from occdata.labels.kernels import NO_LABEL

__all__ = ["points_in_boxes_reference", "vote_voxels_reference", "nearest_labels_reference"]


def points_in_boxes_reference(points: np.ndarray, T_box_from_world: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """Numpy twin of `points_in_boxes`."""
    out = np.full(len(points), -1, np.int32)
    for b in range(len(T_box_from_world) - 1, -1, -1):  # reverse, so the first box wins
        out[points_in_box(points, T_box_from_world[b], half_size[b])] = b
    return out


def vote_voxels_reference(
    points: np.ndarray, classes: np.ndarray, T_grid_from_world: np.ndarray, lower: np.ndarray, voxel_size: float,
    shape: np.ndarray, n_classes: int,
) -> np.ndarray:
    """Numpy twin of `vote_voxels`."""
    shape = tuple(int(s) for s in shape)
    keep = classes < n_classes
    p = points[keep] @ T_grid_from_world[:3, :3].T + T_grid_from_world[:3, 3]
    idx = np.floor((p - lower) / voxel_size).astype(np.int64)
    ok = ((idx >= 0) & (idx < np.array(shape))).all(axis=1)
    flat = np.ravel_multi_index(tuple(idx[ok].T), shape)
    return flat * n_classes + classes[keep][ok].astype(np.int64)


def nearest_labels_reference(query: np.ndarray, ref: np.ndarray, ref_cls: np.ndarray, radius: float) -> np.ndarray:
    """Numpy twin of `nearest_labels`: brute force over all references (small inputs only)."""
    out = np.full(len(query), NO_LABEL, np.uint8)
    for q in range(len(query)):
        d2 = ((ref - query[q]) ** 2).sum(axis=1)
        j = int(np.argmin(d2)) if len(ref) else -1
        if j >= 0 and d2[j] <= radius * radius:
            out[q] = ref_cls[j]
    return out
