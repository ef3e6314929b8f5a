"""Interpolation sampling: image features at the fine voxel centres, averaged over cameras
(docs/design.md#the-network)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occdata.constants import OccGrid

from .geometry import project_points_to_feature, voxel_centres
from .inputs import SceneInputs
from .view_transform import CalibrationCache

__all__ = ["InterpolationSampler", "PairIndex", "SamplingIndex"]


@dataclass(frozen=True)
class SamplingIndex:
    """A sparse (B*V) x (B*N*h*w) matrix in CSR-like bags for `embedding_bag`.

    rows: `(E,) int64` into the flattened channels-last feature table `(B*N*h*w, C)`.
    weights: `(E,) float32` bilinear weight / number of cameras that see the voxel.
    offsets: `(B*V,) int64` start of each voxel's entries (voxels seen by no camera have none -> 0).
    """

    rows: Tensor
    weights: Tensor
    offsets: Tensor


@dataclass(frozen=True)
class PairIndex:
    """The same sparse matrix for the CPU kernels (`sampling_kernels`): offsets `(B*V + 1,) int64`,
    rows `(E, 4) int64`, weights `(E, 4) float32` (numpy), and the number of feature-table rows."""

    offsets: np.ndarray
    rows: np.ndarray
    weights: np.ndarray
    n_rows: int


class _BagSumCPU(torch.autograd.Function):
    """out = S table and grad_table = S^T grad_out with the numba kernels (S = the PairIndex)."""

    @staticmethod
    def forward(ctx, table: Tensor, index: PairIndex) -> Tensor:  # noqa: ANN001
        from .sampling_kernels import bag_forward

        ctx.index = index
        out = bag_forward(table.detach().contiguous().numpy(), index.offsets, index.rows, index.weights)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor, None]:  # noqa: ANN001
        from .sampling_kernels import bag_backward

        index: PairIndex = ctx.index
        chunks = max(1, min(torch.get_num_threads(), numba_threads()))
        grad = bag_backward(grad_out.contiguous().numpy(), index.offsets, index.rows, index.weights, index.n_rows,
                            chunks)
        return torch.from_numpy(grad), None


def numba_threads() -> int:
    """Threads the numba kernels may use: torch's setting, within numba's own limit."""
    import numba

    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


def _use_cpu_kernels(feat: Tensor) -> bool:
    """The numba path: CPU float32 tensors in eager mode (tracing/export and other devices use torch)."""
    tracing = torch.jit.is_tracing() or torch.onnx.is_in_onnx_export() or torch.compiler.is_compiling()
    return feat.device.type == "cpu" and feat.dtype == torch.float32 and not tracing


class InterpolationSampler(nn.Module):
    """Bilinearly sample `(B*N, C, h, w)` features at every fine voxel centre (projected with M^-1,
    T_keyego_from_cam^-1, K, A) and average over the cameras that see the voxel (0 where none).

    The projection is cached like the LSS indices. The sampling itself is one `embedding_bag`
    (a sparse-dense product), linear in the features, so a 1x1 conv may be applied before it.
    Output: `(B, X, Y, Z, C) float32`, channels last.
    """

    def __init__(self, grid: OccGrid, input_hw: tuple[int, int], stride: int) -> None:
        super().__init__()
        self.grid = grid
        self.input_hw = input_hw
        self.stride = stride
        self._cache: CalibrationCache[SamplingIndex] = CalibrationCache()
        self._pairs: CalibrationCache[PairIndex] = CalibrationCache()

    def clear_cache(self) -> None:
        self._cache.clear()
        self._pairs.clear()

    def pair_index(self, inputs: SceneInputs, feat_hw: tuple[int, int]) -> PairIndex:
        """The sampling matrix for the CPU kernels, cached like `index`."""
        return self._pairs.get(inputs, lambda device: self._build_pairs(inputs, feat_hw))

    def _build_pairs(self, inputs: SceneInputs, feat_hw: tuple[int, int]) -> PairIndex:
        from .sampling_kernels import bilinear_pairs

        numba_threads()
        h, w = feat_hw
        B, N = inputs.batch_size, inputs.num_cams
        points = voxel_centres(self.grid).reshape(-1, 3).numpy()
        T_cam_from_aug = torch.linalg.inv(inputs.bev_aug[:, None] @ inputs.T_keyego_from_cam)[..., :3, :]
        proj = inputs.img_aug @ inputs.K
        parts = [bilinear_pairs(points, T_cam_from_aug[b].float().cpu().numpy(), proj[b].float().cpu().numpy(),
                                self.input_hw, self.stride, feat_hw, row0=b * N * h * w) for b in range(B)]
        starts = np.cumsum([0] + [len(p[1]) for p in parts[:-1]])
        offsets = np.concatenate([p[0][:-1] + s for p, s in zip(parts, starts, strict=True)]
                                 + [[sum(len(p[1]) for p in parts)]]).astype(np.int64)
        return PairIndex(offsets=offsets, rows=np.concatenate([p[1] for p in parts]),
                         weights=np.concatenate([p[2] for p in parts]), n_rows=B * N * h * w)

    def index(self, inputs: SceneInputs, feat_hw: tuple[int, int]) -> SamplingIndex:
        return self._cache.get(inputs, lambda device: self._build(inputs, feat_hw, device))

    def _build(self, inputs: SceneInputs, feat_hw: tuple[int, int], device: torch.device) -> SamplingIndex:
        h, w = feat_hw
        N = inputs.num_cams
        points_aug = voxel_centres(self.grid, device).reshape(-1, 3)
        V = points_aug.shape[0]
        feat_xy, visible = project_points_to_feature(
            points_aug, inputs.K, inputs.T_keyego_from_cam, inputs.img_aug, inputs.bev_aug, self.input_hw, self.stride
        )  # (B, N, V, 2), (B, N, V)
        # pairs ordered by (b, v, n) so the entries come out grouped by voxel (bag) without a sort
        b, v, n = torch.nonzero(visible.permute(0, 2, 1), as_tuple=True)
        xy = feat_xy[b, n, v]
        per_voxel = visible.sum(dim=1).reshape(-1)  # (B*V,) cameras that see each voxel
        inv_count = 1.0 / per_voxel[b * V + v].float()
        x0 = torch.floor(xy[:, 0])
        y0 = torch.floor(xy[:, 1])
        fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
        x0, y0 = x0.long(), y0.long()
        xs = torch.stack([x0, x0 + 1, x0, x0 + 1], dim=1)  # (P, 4) bilinear corners
        ys = torch.stack([y0, y0, y0 + 1, y0 + 1], dim=1)
        wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=1)
        inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)  # zero padding: outside corners weigh 0
        rows = ((b * N + n)[:, None] * h + ys.clamp(0, h - 1)) * w + xs.clamp(0, w - 1)
        weights = torch.where(inside, wts * inv_count[:, None], torch.zeros_like(wts))
        per_bag = 4 * per_voxel
        offsets = torch.cumsum(per_bag, 0) - per_bag
        return SamplingIndex(rows=rows.reshape(-1), weights=weights.reshape(-1), offsets=offsets)

    def forward(self, feat: Tensor, inputs: SceneInputs) -> Tensor:
        """feat `(B*N, C, h, w)` -> P `(B, X, Y, Z, C)` (channels last)."""
        _, C, h, w = feat.shape
        table = feat.permute(0, 2, 3, 1).reshape(-1, C)
        if _use_cpu_kernels(feat):
            out = _BagSumCPU.apply(table, self.pair_index(inputs, (h, w)))
            return out.view(inputs.batch_size, *self.grid.shape, C)
        index = self.index(inputs, (h, w))
        out = F.embedding_bag(index.rows, table, index.offsets, mode="sum", per_sample_weights=index.weights)
        return out.view(inputs.batch_size, *self.grid.shape, C)
