"""FastOcc at batch 1 on one fixed rig, with all geometry precomputed as constant buffers.

This is the module `fastocc export` traces. It reuses the network's own layers; only the geometry
changes form so that the graph needs standard operators only:

- LSS pooling: the flat voxel index of every frustum point (the network's cached `PoolingIndex`) is a
  constant; pooling is one Gather + one ScatterND(add) (ONNX opset >= 16).
- Interpolation sampling: the 6 feature maps are stacked into one "atlas" image with a zero row
  between cameras, and each fine voxel samples it with ONE GridSample per camera slot (slot j = the
  j-th camera that sees the voxel), weighted by 1 / (cameras seeing it). GridSample's zero padding and
  the zero rows reproduce the network's rule "corners outside the map weigh 0" exactly.
- Temporal fusion: the queue is an explicit input/output; the runtime supplies T_prev_from_cur per
  queued frame (computed in float64 from the ego poses, so the graph needs no matrix inverse).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fastocc.model import FastOcc, HeadKind
from fastocc.model.geometry import project_points_to_feature, voxel_centres
from fastocc.model.network import collapse_z
from fastocc.model.temporal import warp_bev_inverse
from fastocc.model.view_transform import PoolingIndex, lss_pool

from .rig import Rig

__all__ = ["StaticFastOcc"]


class StaticFastOcc(nn.Module):
    """`forward(images (1, N, 3, H, W) float32[, history (1, T, C, 100, 100), T_prev_from_cur (1, T, 4, 4),
    seq_start (1,) bool])` -> logits `(1, 18, 200, 200, 16) float32`, semantics `(1, 200, 200, 16) uint8`
    [, the next history]. The temporal arguments exist only when the network has a queue
    (`num_history` > 0); C = C2 * 8 (V_B with z collapsed into channels)."""

    def __init__(self, model: FastOcc, rig: Rig) -> None:
        super().__init__()
        cfg = model.cfg
        rig.check_cams(cfg.num_cams)
        self.cfg = cfg
        self.net = model
        H, W = cfg.input_hw
        h, w = cfg.feat_hw
        geo = rig.scene_inputs(torch.zeros(1, cfg.num_cams, 3, H, W))
        index = model.pooling.index(geo, (h, w))
        model.pooling.clear_cache()
        self.register_buffer("point_idx", index.point_idx.clone())
        self.register_buffer("voxel_idx", index.voxel_idx.clone())
        self.num_slots = 0
        if cfg.head is HeadKind.FASTOCC:
            grids, weights = _atlas_sampling(geo, cfg.fine_grid, cfg.input_hw, cfg.stride, (h, w))
            self.num_slots = grids.shape[0]
            self.register_buffer("slot_grids", grids)  # (S, 1, V, 1, 2)
            self.register_buffer("slot_weights", weights)  # (S, 1, 1, V)
        if model.temporal is not None:
            self.register_buffer("bev_identity", torch.eye(4))

    @property
    def temporal(self) -> bool:
        return self.net.temporal is not None

    def history_shape(self) -> tuple[int, ...]:
        X, Y, Z = self.cfg.coarse_grid.shape
        return (1, self.cfg.num_history, self.cfg.context_channels * Z, X, Y)

    def example_inputs(self, seed: int = 0) -> tuple[Tensor, ...]:
        g = torch.Generator().manual_seed(seed)
        H, W = self.cfg.input_hw
        images = torch.randn(1, self.cfg.num_cams, 3, H, W, generator=g)
        if not self.temporal:
            return (images,)
        T = self.cfg.num_history
        return (images, torch.zeros(self.history_shape()), torch.eye(4).expand(1, T, 4, 4).clone(),
                torch.ones(1, dtype=torch.bool))

    def input_names(self) -> list[str]:
        return ["images", "history", "T_prev_from_cur", "seq_start"] if self.temporal else ["images"]

    def output_names(self) -> list[str]:
        return ["logits", "semantics", "history_out"] if self.temporal else ["logits", "semantics"]

    def forward(self, images: Tensor, history: Tensor | None = None, T_prev_from_cur: Tensor | None = None,
                seq_start: Tensor | None = None) -> tuple[Tensor, ...]:
        net, cfg = self.net, self.cfg
        feat = net.image_stage(images)  # (N, C1, h, w)
        depth, context = net.depth_net(feat)
        pooled = lss_pool(depth, context, PoolingIndex(self.point_idx, self.voxel_idx), 1, cfg.coarse_grid.shape)
        bev = collapse_z(pooled)  # (1, C2*8, 100, 100)
        new_history = None
        if self.temporal:
            assert history is not None and T_prev_from_cur is not None and seq_start is not None
            T = cfg.num_history
            # a sequence start fills the queue with the current frame (identity poses from the runtime)
            feats = torch.where(seq_start.view(1, 1, 1, 1, 1), bev.unsqueeze(1).expand_as(history), history)
            C, X, Y = bev.shape[1:]
            warped = warp_bev_inverse(feats.reshape(T, C, X, Y), T_prev_from_cur.reshape(T, 4, 4), cfg.coarse_grid)
            new_history = torch.cat([bev.unsqueeze(1), feats[:, :-1]], dim=1)
            bev = net.temporal.reduce(torch.cat([bev, warped.reshape(1, T * C, X, Y)], dim=1))
        logits = self._head(feat, bev)
        semantics = logits.argmax(dim=1).to(torch.uint8)
        return (logits, semantics) if new_history is None else (logits, semantics, new_history)

    def _head(self, feat: Tensor, bev: Tensor) -> Tensor:
        head = self.net.head
        if self.cfg.head is not HeadKind.FASTOCC:
            return head(feat, bev, None)[0]
        X, Y, Z = self.cfg.fine_grid.shape
        bev_part = F.interpolate(head.fuse_bev(head.decoder(bev)), size=(X, Y), mode="bilinear", align_corners=False)
        img = head.fuse_img(feat)  # (N, Cf, h, w)
        N, Cf, h, w = img.shape
        # atlas (1, Cf, N (h+1), w): cameras stacked along rows, one zero row after each
        atlas = F.pad(img, (0, 0, 0, 1)).permute(1, 0, 2, 3).reshape(1, Cf, N * (h + 1), w)
        sampled = None
        for s in range(self.num_slots):
            part = F.grid_sample(atlas, self.slot_grids[s], mode="bilinear", padding_mode="zeros",
                                 align_corners=False)[..., 0] * self.slot_weights[s]  # (1, Cf, V)
            sampled = part if sampled is None else sampled + part
        assert sampled is not None
        fused = F.relu(sampled.view(1, Cf, X, Y, Z) + bev_part.unsqueeze(-1))  # z-repeat by broadcasting
        weight = head.classifier.weight.view(*head.classifier.weight.shape, 1, 1, 1)
        return F.conv3d(fused, weight, head.classifier.bias)


def _atlas_sampling(geo, grid, input_hw: tuple[int, int], stride: int,  # noqa: ANN001
                    feat_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """GridSample coordinates `(S, 1, V, 1, 2)` into the camera atlas and weights `(S, 1, 1, V)` per slot.

    Slot j of voxel v is the j-th camera (in camera order) that sees v; voxels with fewer than j + 1
    cameras point far outside the atlas (GridSample gives 0) and weigh 0.
    """
    h, w = feat_hw
    points = voxel_centres(grid).reshape(-1, 3)
    feat_xy, visible = project_points_to_feature(points, geo.K, geo.T_keyego_from_cam, geo.img_aug, geo.bev_aug,
                                                 input_hw, stride)
    feat_xy, visible = feat_xy[0].double(), visible[0]  # (N, V, 2), (N, V)
    N = visible.shape[0]
    count = visible.sum(0)  # (V,)
    rank = visible.long().cumsum(0) - 1  # rank of each camera among those that see the voxel
    atlas_h = N * (h + 1)
    rows = torch.arange(N, dtype=torch.float64).view(N, 1) * (h + 1)
    grids, weights = [], []
    for s in range(int(count.max())):
        pick = visible & (rank == s)  # (N, V): at most one camera per voxel
        has = pick.any(0)
        cam = pick.double().argmax(0)
        xy = feat_xy.gather(0, cam.view(1, -1, 1).expand(1, -1, 2))[0]  # (V, 2)
        ay = rows[cam, 0] + xy[:, 1]
        g = torch.stack([(2 * xy[:, 0] + 1) / w - 1, (2 * ay + 1) / atlas_h - 1], dim=-1)
        g = torch.where(has[:, None], g, torch.full_like(g, -4.0))
        grids.append(g.float().view(1, -1, 1, 2))
        weights.append(torch.where(has, 1.0 / count.clamp_min(1).double(), 0.0).float().view(1, 1, -1))
    return torch.stack(grids), torch.stack(weights)
