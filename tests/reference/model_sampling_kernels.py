"""Test oracles for `fastocc.model.sampling_kernels`: plain numpy twins of its numba kernels, which the tests
compare the kernels against (moved out of the product module; nothing in fastocc uses them)."""

from __future__ import annotations

import numpy as np

__all__ = ["bilinear_pairs_numpy", "bag_forward_numpy", "bag_backward_numpy"]


def bilinear_pairs_numpy(points: np.ndarray, cam: np.ndarray, proj: np.ndarray, input_hw: tuple[int, int],
                         stride: int, feat_hw: tuple[int, int], row0: int = 0, min_depth: float = 0.1
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain numpy twin of `bilinear_pairs` (same outputs)."""
    H, W = input_hw
    h, w = feat_hw
    p_cam = np.einsum("nij,vj->vni", cam[:, :, :3], points) + cam[None, :, :, 3]  # (V, N, 3)
    uvw = np.einsum("nij,vnj->vni", proj, p_cam)
    uv = uvw[..., :2] / np.maximum(uvw[..., 2:3], np.float32(1e-6))
    ok = (p_cam[..., 2] > min_depth) & (uv[..., 0] >= 0) & (uv[..., 0] <= W - 1) & (uv[..., 1] >= 0) & (
        uv[..., 1] <= H - 1)
    counts = ok.sum(axis=1)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    v_idx, n_idx = np.nonzero(ok)  # row-major: grouped by voxel, cameras ascending
    f = (uv[v_idx, n_idx] - np.float32((stride - 1) / 2.0)) / stride
    x0, y0 = np.floor(f[:, 0]), np.floor(f[:, 1])
    ax, ay = f[:, 0] - x0, f[:, 1] - y0
    xs = x0.astype(np.int64)[:, None] + np.array([0, 1, 0, 1])
    ys = y0.astype(np.int64)[:, None] + np.array([0, 0, 1, 1])
    wts = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], axis=1) / counts[v_idx, None]
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    rows = row0 + n_idx[:, None] * h * w + np.where(inside, ys * w + xs, 0)
    return offsets, rows.astype(np.int64), np.where(inside, wts, 0).astype(np.float32)


def bag_forward_numpy(table: np.ndarray, offsets: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Plain numpy twin of `bag_forward`."""
    voxel = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    out = np.zeros((len(offsets) - 1, table.shape[1]), dtype=np.float32)
    np.add.at(out, voxel, (weights[:, :, None] * table[rows]).sum(axis=1))
    return out


def bag_backward_numpy(grad_out: np.ndarray, offsets: np.ndarray, rows: np.ndarray, weights: np.ndarray,
                       n_rows: int) -> np.ndarray:
    """Plain numpy twin of `bag_backward`."""
    voxel = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    grad = np.zeros((n_rows, grad_out.shape[1]), dtype=np.float32)
    np.add.at(grad, rows.reshape(-1), (weights[:, :, None] * grad_out[voxel][:, None, :]).reshape(-1, grad.shape[1]))
    return grad
