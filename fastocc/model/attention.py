"""2D -> 3D view transform by spatial cross-attention (BEVFormer / SurroundOcc style), pure PyTorch.

The paper's "SurroundOcc*" row (Table II) replaces LSS by a transformer view transform and decodes with the
3D deconvolution head. Here: one learned query per coarse voxel (100 x 100 x 8), its reference point the
voxel centre projected into every camera; per camera, `heads` x `points` deformable samples around the
reference point (offsets and attention weights predicted from the query, sampling by `F.grid_sample`, no
custom operator), summed with the softmax weights, averaged over the cameras that see the voxel (only the
(voxel, camera) pairs where the centre is seen are sampled: ~1.04 of 6 cameras per seen voxel); an output
projection, a residual, LayerNorm and a feed-forward layer. Its output takes V_B's place, `(B, C2, 100, 100,
8)`, so every head can decode it. Simplifications against SurroundOcc: one attention layer, one feature
scale, no 3D self-attention; queries are a sum of per-axis embeddings (x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import ModelConfig
from .geometry import project_points_to_feature, voxel_centres
from .inputs import SceneInputs
from .view_transform import CalibrationCache

__all__ = ["AttentionGeometry", "SpatialCrossAttention", "attention_geometry"]


@dataclass(frozen=True)
class AttentionGeometry:
    """Where the coarse voxel centres land in the cameras, as M slots per camera image: slot j of image
    i = b N + n is the j-th voxel (in grid order) that camera n of sample b sees; cameras that see fewer
    voxels than the busiest one pad their slots (valid 0). Only these (voxel, camera) pairs are sampled.

    ref: `(B*N, M, 2) float32` grid_sample coordinates (align_corners=False, x then y) of the slot's voxel
        centre in the camera's feature map.
    query: `(B*N, M) int64` the slot's voxel (0 .. Q-1; 0 in padded slots).
    target: `(B*N, M) int64` the slot's row b Q + q in the `(B*Q + 1)` output; padded slots point at the
        last, discarded row.
    valid: `(B*N, M) float32` 1 for a real slot, 0 for padding.
    count: `(B, Q) float32` cameras that see each voxel, at least 1.
    """

    ref: Tensor
    query: Tensor
    target: Tensor
    valid: Tensor
    count: Tensor


def attention_geometry(inputs: SceneInputs, cfg: ModelConfig, feat_hw: tuple[int, int],
                       device: torch.device | None = None) -> AttentionGeometry:
    """Project the coarse voxel centres `(Q = X Y Z)` of the augmented key-ego grid into every camera: a centre
    counts as seen when it is in front of the camera and inside its image."""
    points = voxel_centres(cfg.coarse_grid, device).reshape(-1, 3)
    feat_xy, visible = project_points_to_feature(points, inputs.K, inputs.T_keyego_from_cam, inputs.img_aug,
                                                 inputs.bev_aug, cfg.input_hw, cfg.stride)  # (B, N, Q, 2)
    h, w = feat_hw
    B, N, Q = visible.shape
    size = torch.tensor([w, h], dtype=feat_xy.dtype, device=feat_xy.device)
    norm = (feat_xy + 0.5) / size * 2 - 1  # cell centres at integers -> grid_sample's normalised coordinates
    seen = visible.sum(-1)  # (B, N)
    M = max(1, int(seen.max()))
    order = torch.sort((~visible).to(torch.int8), dim=-1, stable=True).indices[..., :M]  # seen voxels first
    valid = torch.arange(M, device=visible.device) < seen[..., None]  # (B, N, M)
    query = torch.where(valid, order, torch.zeros_like(order))
    ref = torch.gather(norm, 2, query[..., None].expand(B, N, M, 2)).clamp(-2.0, 2.0)
    rows = torch.arange(B, device=visible.device).view(B, 1, 1) * Q + query
    target = torch.where(valid, rows, torch.full_like(rows, B * Q))
    return AttentionGeometry(ref=ref.reshape(B * N, M, 2), query=query.reshape(B * N, M),
                             target=target.reshape(B * N, M), valid=valid.reshape(B * N, M).float(),
                             count=visible.sum(1).clamp_min(1).float())


class SpatialCrossAttention(nn.Module):
    """Image features F `(B*N, C1, h, w)` -> a voxel volume `(B, C2, X, Y, Z)` on the coarse grid."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        C = cfg.context_channels
        self.cfg = cfg
        self.grid_shape = cfg.coarse_grid.shape
        self.heads, self.points = cfg.attention_heads, cfg.attention_points
        self.value = nn.Conv2d(cfg.neck_channels, C, 1)
        self.embed = nn.ParameterList([nn.Parameter(0.02 * torch.randn(n, C)) for n in self.grid_shape])
        self.offsets = nn.Linear(C, self.heads * self.points * 2)
        self.weights = nn.Linear(C, self.heads * self.points)
        self.out = nn.Linear(C, C)
        self.norm1 = nn.LayerNorm(C)
        self.ffn = nn.Sequential(nn.Linear(C, 2 * C), nn.ReLU(inplace=True), nn.Linear(2 * C, C))
        self.norm2 = nn.LayerNorm(C)
        self._reset_sampling()
        self._cache: CalibrationCache[AttentionGeometry] = CalibrationCache()

    def _reset_sampling(self) -> None:
        """Deformable-DETR-style start: zero offset weights, the offsets' bias a ring of `points` samples per head
        (head k's ring turned by k / heads of a turn; radius 1, 2, ... feature cells), uniform attention."""
        nn.init.zeros_(self.offsets.weight)
        angles = torch.arange(self.heads).float()[:, None] / self.heads * 2 * torch.pi
        angles = angles + torch.arange(self.points).float()[None] / self.points * 2 * torch.pi
        radius = torch.arange(1, self.points + 1).float()[None].expand(self.heads, -1)
        ring = torch.stack([angles.cos(), angles.sin()], dim=-1) * radius[..., None]  # (heads, points, 2)
        with torch.no_grad():
            self.offsets.bias.copy_(ring.reshape(-1))
        nn.init.zeros_(self.weights.weight)
        nn.init.zeros_(self.weights.bias)

    def clear_cache(self) -> None:
        self._cache.clear()

    def queries(self) -> Tensor:
        """`(Q, C)`: the embedding of voxel (x, y, z) is e_x[x] + e_y[y] + e_z[z], x-major like V_B."""
        ex, ey, ez = self.embed
        return (ex[:, None, None] + ey[None, :, None] + ez[None, None, :]).reshape(-1, ex.shape[1])

    def forward(self, feat: Tensor, inputs: SceneInputs) -> Tensor:
        """feat `(B*N, C1, h, w)` -> `(B, C2, X, Y, Z)`; the projection is cached per calibration."""
        h, w = feat.shape[2:]
        geo = self._cache.get(inputs, lambda device: attention_geometry(inputs, self.cfg, (h, w), device))
        return self.attend(feat, geo)

    def attend(self, feat: Tensor, geo: AttentionGeometry) -> Tensor:
        """The attention itself, given the geometry (the export wrapper bakes it as constants)."""
        BN, _, h, w = feat.shape
        B = geo.count.shape[0]
        M = geo.ref.shape[1]
        H, P = self.heads, self.points
        q = self.queries()  # (Q, C)
        Q, C = q.shape
        value = self.value(feat).reshape(BN * H, C // H, h, w)
        cells = torch.tensor([2.0 / w, 2.0 / h], dtype=feat.dtype, device=feat.device)  # one cell, normalised
        slots = geo.query.reshape(-1)
        offsets = self.offsets(q).index_select(0, slots).view(BN, M, H, P, 2) * cells
        loc = (geo.ref.view(BN, M, 1, 1, 2) + offsets).permute(0, 2, 1, 3, 4).reshape(BN * H, M, P, 2)
        sampled = F.grid_sample(value, loc, mode="bilinear", padding_mode="zeros", align_corners=False)
        attn = self.weights(q).view(Q, H, P).softmax(dim=-1).index_select(0, slots).view(BN, M, H, P)
        per_slot = (sampled.view(BN, H, C // H, M, P) * attn.permute(0, 2, 1, 3)[:, :, None]).sum(-1)
        rows = (per_slot.reshape(BN, C, M) * geo.valid[:, None]).permute(0, 2, 1).reshape(BN * M, C)
        summed = rows.new_zeros(B * Q + 1, C).index_add_(0, geo.target.reshape(-1), rows)[: B * Q]
        x = summed.view(B, Q, C) / geo.count[..., None]  # mean over the cameras that see the voxel
        x = self.norm1(q + self.out(x))
        x = self.norm2(x + self.ffn(x))
        X, Y, Z = self.grid_shape
        return x.transpose(1, 2).reshape(B, C, X, Y, Z)
