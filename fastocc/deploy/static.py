"""FastOcc at batch 1 on one fixed rig, with all geometry precomputed as constant buffers.

This is the module `fastocc export` traces. It reuses the network's own layers; only the geometry
changes form so that the graph needs standard operators only:

- LSS pooling: the flat voxel index of every frustum point (the network's cached `PoolingIndex`) is a
  constant; pooling is one Gather + one ScatterND(add) (ONNX opset >= 16).
- Spatial cross-attention (view_transform "attention"): the (voxel, camera) slots, their reference points
  and the camera counts are constants; the deformable sampling is GridSample (opset >= 16), the mean over
  cameras one ScatterND(add).
- Interpolation sampling: bilinear sampling with constant corner rows and weights, as Gathers from a
  channels-last feature table with one zero row appended. Per camera slot (slot j = the j-th camera
  that sees the voxel): 4 Gathers, each times its weight (bilinear weight / cameras seeing the voxel;
  0 for corners outside the map, which point at the zero row), summed. Slot 0 spans all voxels; later
  slots (overlaps between cameras, a few percent of the voxels) are computed compactly and spread back
  with one Gather. (ONNX Runtime's GridSample was 3x slower for the same sampling.)
- Temporal fusion: the queue is an explicit input/output; the runtime supplies T_prev_from_cur per
  queued frame (computed in float64 from the ego poses, so the graph needs no matrix inverse).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fastocc.model import FastOcc, HeadKind
from fastocc.model.attention import AttentionGeometry, attention_geometry
from fastocc.model.geometry import project_points_to_feature, voxel_centres
from fastocc.model.network import collapse_z
from fastocc.model.view_transform import PoolingIndex, lss_pool

from .rig import Rig

__all__ = ["StaticFastOcc"]


class StaticFastOcc(nn.Module):
    """`forward(images (1, N, 3, H, W) float32[, history (1, T, C_q, 100, 100), T_prev_from_cur (1, T, 4, 4),
    seq_start (1,) bool])` -> logits `(1, 18, 200, 200, 16) float32`, semantics `(1, 200, 200, 16) uint8`
    [, the next history]. The temporal arguments exist only when the network has a queue
    (`num_history` > 0); C_q = C2 * 8 (V_B with z collapsed into channels) for the "concat" fusion, C_r for
    the "cached" one (each frame reduced once, when it is current)."""

    def __init__(self, model: FastOcc, rig: Rig) -> None:
        super().__init__()
        cfg = model.cfg
        rig.check_cams(cfg.num_cams)
        self.cfg = cfg
        self.net = model
        H, W = cfg.input_hw
        h, w = cfg.feat_hw
        geo = rig.scene_inputs(torch.zeros(1, cfg.num_cams, 3, H, W))
        if model.attention is not None:
            att = attention_geometry(geo, cfg, (h, w))
            for name in ("ref", "query", "target", "valid", "count"):
                self.register_buffer(f"att_{name}", getattr(att, name).clone())
        else:
            index = model.pooling.index(geo, (h, w))
            model.pooling.clear_cache()
            self.register_buffer("point_idx", index.point_idx.clone())
            self.register_buffer("voxel_idx", index.voxel_idx.clone())
        self.num_slots = 0
        if cfg.head is HeadKind.FASTOCC and cfg.interp_features:
            slots = _slot_sampling(geo, cfg.fine_grid, cfg.input_hw, cfg.stride, (h, w))
            self.num_slots = len(slots)
            for s, (rows, wts, scatter) in enumerate(slots):
                self.register_buffer(f"slot{s}_idx", rows)
                self.register_buffer(f"slot{s}_w", wts)
                if scatter is not None:
                    self.register_buffer(f"slot{s}_scatter", scatter)

    @property
    def temporal(self) -> bool:
        """Whether the graph carries a queue (history in, history out): models with past frames."""
        return self.net.temporal is not None and self.cfg.num_history > 0

    def history_shape(self) -> tuple[int, ...]:
        """`(1, T, C_q, 100, 100)`: C_q = C2 * 8 for the "concat" queue, C_r for the "cached" one; the
        "recurrent" fusion's history is its one state (T = 1, C_q = C_r)."""
        X, Y, _ = self.cfg.coarse_grid.shape
        return (1, self.net.temporal.queue_length, self.net.temporal.queue_channels, X, Y)

    def example_inputs(self, seed: int = 0) -> tuple[Tensor, ...]:
        g = torch.Generator().manual_seed(seed)
        H, W = self.cfg.input_hw
        images = torch.randn(1, self.cfg.num_cams, 3, H, W, generator=g)
        if not self.temporal:
            return (images,)
        T = self.history_shape()[1]
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
        if net.attention is not None:
            pooled = net.attention.attend(feat, AttentionGeometry(self.att_ref, self.att_query, self.att_target,
                                                                  self.att_valid, self.att_count))
        else:
            depth, context = net.depth_net(feat)
            pooled = lss_pool(depth, context, PoolingIndex(self.point_idx, self.voxel_idx), 1, cfg.coarse_grid.shape)
        bev = collapse_z(pooled)  # (1, C2*8, 100, 100)
        new_history = None
        if net.temporal is not None:  # the queue or the recurrent state, as explicit inputs and outputs
            bev, new_history = net.temporal.static_step(bev, history, T_prev_from_cur, seq_start)
        logits, class_dim = self._head(feat, bev)
        semantics = logits.argmax(dim=class_dim).to(torch.uint8)  # before any layout change: cache-friendly
        if class_dim == -1:  # channels-last (X, Y, Z, 18) -> (1, 18, X, Y, Z); skipped when only semantics is asked
            logits = logits.permute(3, 0, 1, 2).unsqueeze(0)
            semantics = semantics.unsqueeze(0)
        return (logits, semantics) if new_history is None else (logits, semantics, new_history)

    def _head(self, feat: Tensor, bev: Tensor) -> tuple[Tensor, int]:
        """Logits and their class dimension: `(1, 18, X, Y, Z)` (1) or channels-last `(X, Y, Z, 18)` (-1)."""
        head = self.net.head
        if self.cfg.head is not HeadKind.FASTOCC:
            return head(feat, bev, None)[0], 1
        X, Y, Z = self.cfg.fine_grid.shape
        bev_z = head.bev_part(head.decoder(bev))[0]  # (X, Y, 1, Cf): z-repeat by broadcasting; or (X, Y, Z, Cf)
        if head.fuse_img is None:  # interp_features off: one classifier call per BEV cell (or per voxel, unfold)
            return head.classifier(F.relu(bev_z)).expand(X, Y, Z, -1), -1
        img = head.fuse_img(feat)  # (N, Cf, h, w)
        Cf = img.shape[1]
        # channels-last feature table with a zero row last: out-of-map corners and absent slots point at it
        table = torch.cat([img.permute(0, 2, 3, 1).reshape(-1, Cf), img.new_zeros(1, Cf)], dim=0)
        sampled = _bilinear(table, self.slot0_idx, self.slot0_w)  # (V, Cf)
        for s in range(1, self.num_slots):
            part = _bilinear(table, getattr(self, f"slot{s}_idx"), getattr(self, f"slot{s}_w"))  # (M_s, Cf)
            part = torch.cat([part, part.new_zeros(1, Cf)], dim=0)
            sampled = sampled + part.index_select(0, getattr(self, f"slot{s}_scatter"))
        fused = F.relu(sampled.view(X, Y, Z, Cf) + bev_z)
        return head.classifier(fused), -1  # (X, Y, Z, 18)


def _bilinear(table: Tensor, idx: Tensor, w: Tensor) -> Tensor:
    """sum_k w[k] * table[idx[k]]: idx `(4, M) int64`, w `(4, M, 1) float32` -> `(M, C)`."""
    out = table.index_select(0, idx[0]) * w[0]
    for k in range(1, idx.shape[0]):
        out = out + table.index_select(0, idx[k]) * w[k]
    return out


def _slot_sampling(geo, grid, input_hw: tuple[int, int], stride: int,  # noqa: ANN001
                   feat_hw: tuple[int, int]) -> list[tuple[Tensor, Tensor, Tensor | None]]:
    """Per camera slot: bilinear corner rows `(4, M) int64` into the `(N*h*w + 1, C)` table (last row zero),
    weights `(4, M, 1) float32` including 1 / (cameras seeing the voxel), and for slots >= 1 the row of
    each voxel in the slot's compacted result `(V,) int64` (M = its zero row where the slot is absent).

    Slot j of voxel v is the j-th camera (in camera order) that sees v. Slot 0 spans all V voxels.
    """
    h, w = feat_hw
    points = voxel_centres(grid).reshape(-1, 3)
    feat_xy, visible = project_points_to_feature(points, geo.K, geo.T_keyego_from_cam, geo.img_aug, geo.bev_aug,
                                                 input_hw, stride)
    feat_xy, visible = feat_xy[0], visible[0]  # (N, V, 2) float32 as the network computes it, (N, V)
    N, V = visible.shape
    zero_row = N * h * w
    count = visible.sum(0)  # (V,)
    rank = visible.long().cumsum(0) - 1  # rank of each camera among those that see the voxel
    slots: list[tuple[Tensor, Tensor, Tensor | None]] = []
    for s in range(int(count.max())):
        pick = visible & (rank == s)  # (N, V): at most one camera per voxel
        has = pick.any(0)
        vox = torch.arange(V) if s == 0 else torch.nonzero(has).squeeze(1)
        cam = pick.long().argmax(0)[vox]
        xy = feat_xy[cam, vox]  # (M, 2)
        x0, y0 = torch.floor(xy[:, 0]), torch.floor(xy[:, 1])
        fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
        x0, y0 = x0.long(), y0.long()
        xs = torch.stack([x0, x0 + 1, x0, x0 + 1])
        ys = torch.stack([y0, y0, y0 + 1, y0 + 1])
        wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])  # (4, M)
        ok = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h) & has[vox]
        rows = torch.where(ok, (cam * h + ys.clamp(0, h - 1)) * w + xs.clamp(0, w - 1), zero_row)
        wts = torch.where(ok, wts / count[vox].clamp_min(1).float(), 0.0)
        scatter = None
        if s > 0:
            scatter = torch.full((V,), vox.numel(), dtype=torch.long)
            scatter[vox] = torch.arange(vox.numel())
        slots.append((rows, wts.unsqueeze(-1).float(), scatter))
    return slots
