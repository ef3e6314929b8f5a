"""Temporal fusion: a queue of previous BEV features warped by ego motion (docs/design.md#the-network)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occdata.constants import OccGrid

from .config import TEMPORAL_CHANNELS, TemporalFusionKind
from .geometry import voxel_centres
from .inputs import SceneInputs

__all__ = ["TemporalFusion", "T_curaug_from_prevaug", "warp_bev", "warp_bev_inverse"]


def T_curaug_from_prevaug(T_global_from_cur: Tensor, M_cur: Tensor, T_global_from_prev: Tensor,
                          M_prev: Tensor) -> Tensor:
    """Previous augmented key ego -> current augmented key ego: `M_cur inv(T_g_from_cur) T_g_from_prev inv(M_prev)`.

    All `(..., 4, 4)`, broadcast. The poses are the store's `T_global_from_keyego` (LIDAR_TOP ego at
    the keyframe); M is the BEV augmentation (identity at test time). This is what the queue warps by.
    """
    return M_cur @ torch.linalg.inv(T_global_from_cur) @ T_global_from_prev @ torch.linalg.inv(M_prev)


def warp_bev(feat_prev: Tensor, T_curaug_from_prevaug: Tensor, grid: OccGrid) -> Tensor:
    """Resample previous BEV features into the current frame.

    feat_prev `(B, C, X, Y)` in the previous augmented key ego; T_curaug_from_prevaug `(B, 4, 4)`.
    Each current cell centre (z = 0 plane) is mapped back into the previous frame and sampled
    bilinearly (zeros outside). Returns `(B, C, X, Y)`.
    """
    return warp_bev_inverse(feat_prev, torch.linalg.inv(T_curaug_from_prevaug), grid)


def warp_bev_inverse(feat_prev: Tensor, T_prevaug_from_curaug: Tensor, grid: OccGrid) -> Tensor:
    """`warp_bev` given the inverse transform `(B, 4, 4)` (no matrix inverse in the graph: ONNX export)."""
    centres = voxel_centres(grid, feat_prev.device)[:, :, 0, :2].to(feat_prev.dtype)  # float64 features: float64
    pts = torch.cat([centres, torch.zeros_like(centres[..., :1]), torch.ones_like(centres[..., :1])], dim=-1)
    prev = torch.einsum("bij,xyj->bxyi", T_prevaug_from_curaug, pts)[..., :2]  # (B, X, Y, 2) metres
    lo = torch.tensor(grid.lower[:2], dtype=prev.dtype, device=prev.device)
    hi = torch.tensor(grid.upper[:2], dtype=prev.dtype, device=prev.device)
    norm = (prev - lo) / (hi - lo) * 2 - 1  # align_corners=False: cell centres at their normalised spots
    # grid_sample indexes (W, H) = (Y, X) of a (B, C, X, Y) tensor: swap to (y, x)
    return F.grid_sample(feat_prev, norm.flip(-1), mode="bilinear", padding_mode="zeros", align_corners=False)


class TemporalFusion(nn.Module):
    """Fuse the current BEV feature with `num_history` previous ones warped into the current frame.

    kind "concat": the queue holds each frame's full map (C channels); the fusion is a 1x1 conv + BN + ReLU
    over concat(current, T warped maps), (T + 1) C -> C channels (`reduce`).
    kind "cached": each frame's map is reduced ONCE, when it is the current frame, by a linear 1x1 conv
    C -> C_r (`compress`; no normalisation, so a queued map is the same function of the weights in training
    and at inference); the queue holds these reduced maps. Per frame only the warp of T maps of C_r
    channels and a small residual fusion run: fused = bev + expand(relu(BN(mix(concat(current reduced map,
    T warped reduced maps))))), mix (T + 1) C_r -> 2 C_r, expand 2 C_r -> C (1x1 convs). `mix` is applied
    as two convs (current part, history part) summed, which equals the conv of the concatenation without
    materialising it. The current reduced map is in the fusion so that `compress` gets a gradient (the
    queued copies are detached, as in the "concat" queue).

    The queue holds detached per-frame maps (nearest first) with their T_global_from_keyego and BEV
    augmentation M. Where `seq_start` is True (or on the first call) the queue of that sample is filled with
    the current frame, so the channel count never changes. A batch smaller than the last keeps the first
    rows of the queue (lanes that ended were the last rows). Per-frame cost is one warp of `num_history`
    maps, whatever the length of the stream. `num_history` 0 (the fusion-layer control) has no queue: the
    current frame alone goes through the fusion layer.
    """

    def __init__(self, channels: int, num_history: int, grid: OccGrid,
                 kind: TemporalFusionKind = TemporalFusionKind.CONCAT,
                 cached_channels: int = TEMPORAL_CHANNELS[TemporalFusionKind.CACHED],
                 grad_history: bool = False) -> None:
        super().__init__()
        self.num_history = num_history
        self.grid = grid
        self.kind = TemporalFusionKind(kind)
        # "cached" in training: queue the full maps, reduce them with gradient (ModelConfig.temporal_grad_history)
        self.grad_history = grad_history and self.kind is TemporalFusionKind.CACHED
        T, C = num_history, channels
        if self.kind is TemporalFusionKind.CACHED:
            c_r, c_m = cached_channels, 2 * cached_channels
            self.queue_channels = c_r
            self.compress = nn.Conv2d(C, c_r, 1)
            self.mix_current = nn.Conv2d(c_r, c_m, 1, bias=False)
            self.mix_history = nn.Conv2d(T * c_r, c_m, 1, bias=False) if T > 0 else None
            self.mix_norm = nn.Sequential(nn.BatchNorm2d(c_m), nn.ReLU(inplace=True))
            self.expand = nn.Conv2d(c_m, C, 1)
        else:
            self.queue_channels = C
            self.reduce = nn.Sequential(
                nn.Conv2d(C * (T + 1), C, 1, bias=False),
                nn.BatchNorm2d(C),
                nn.ReLU(inplace=True),
            )
        self.queue_length = T  # the ONNX graph's history: T queued maps
        self._feats: Tensor | None = None  # (B, T, C_q, X, Y)
        self._poses: Tensor | None = None  # (B, T, 4, 4) T_global_from_keyego
        self._bev_aug: Tensor | None = None  # (B, T, 4, 4) M

    def reset(self) -> None:
        self._feats = self._poses = self._bev_aug = None

    def queue_state(self) -> tuple[Tensor, Tensor, Tensor] | None:
        """The queue (features `(B, T, C_q, X, Y)`, poses and BEV augmentations `(B, T, 4, 4)`), detached on
        the CPU; None when empty. `load_queue_state` restores it exactly (checkpoints, validation)."""
        if self._feats is None:
            return None
        return tuple(v.detach().cpu() for v in (self._feats, self._poses, self._bev_aug))  # type: ignore[return-value]

    def load_queue_state(self, state: tuple[Tensor, Tensor, Tensor] | list[Tensor] | None,
                         device: torch.device | str | None = None) -> None:
        """Inverse of `queue_state` (None empties the queue); tensors go to `device` (default: the weights')."""
        if state is None:
            self.reset()
            return
        dev = device if device is not None else next(self.parameters()).device
        self._feats, self._poses, self._bev_aug = (v.to(dev) for v in state)

    def queue_entry(self, bev: Tensor) -> Tensor:
        """What a frame contributes to the queue: `(B, C, X, Y)` -> `(B, C_q, X, Y)` (C_r when cached)."""
        return self.compress(bev) if self.kind is TemporalFusionKind.CACHED else bev

    def fuse(self, bev: Tensor, entry: Tensor, warped: Tensor | None) -> Tensor:
        """The fusion layer: current map `(B, C, X, Y)`, its queue entry `(B, C_q, X, Y)` and the warped
        queue `(B, T C_q, X, Y)` (None without history) -> `(B, C, X, Y)`."""
        if self.kind is TemporalFusionKind.CACHED:
            mixed = self.mix_current(entry)
            if warped is not None:
                mixed = mixed + self.mix_history(warped)
            return bev + self.expand(self.mix_norm(mixed))
        return self.reduce(bev if warped is None else torch.cat([bev, warped], dim=1))

    def static_step(self, bev: Tensor, history: Tensor | None, T_prev_from_cur: Tensor | None,
                    seq_start: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """The export graph's step: bev `(1, C, X, Y)`, the queue `(1, T, C_q, X, Y)`, T_prev_from_cur
        `(1, T, 4, 4)`, seq_start `(1,)` -> fused `(1, C, X, Y)` and the next queue (None without history:
        the zero-history control). A sequence start fills the queue with the current frame (the runtime
        gives identity poses)."""
        entry = self.queue_entry(bev)
        if history is None or T_prev_from_cur is None or seq_start is None:
            return self.fuse(bev, entry, None), None
        T, (Cq, X, Y) = self.num_history, entry.shape[1:]
        feats = torch.where(seq_start.view(1, 1, 1, 1, 1), entry.unsqueeze(1).expand_as(history), history)
        warped = warp_bev_inverse(feats.reshape(T, Cq, X, Y), T_prev_from_cur.reshape(T, 4, 4),
                                  self.grid).reshape(1, T * Cq, X, Y)
        return self.fuse(bev, entry, warped), torch.cat([entry.unsqueeze(1), feats[:, :-1]], dim=1)

    def forward(self, bev: Tensor, inputs: SceneInputs) -> Tensor:
        """bev `(B, C, X, Y)` in the current augmented frame -> fused `(B, C, X, Y)`."""
        entry = self.queue_entry(bev)
        if self.num_history == 0:
            return self.fuse(bev, entry, None)
        full = self.grad_history and self.training
        stored = bev if full else entry  # what the queue keeps of this frame
        B, Cq, X, Y = stored.shape
        T = self.num_history
        pose = inputs.T_global_from_keyego
        if pose is None:
            pose = torch.eye(4, device=bev.device).expand(B, 4, 4)
        start = inputs.seq_start
        if start is not None and self._feats is not None and self._feats.shape[0] > B:
            # Lanes that ended leave a batch from its end (fastocc.data.order keeps the live lanes first).
            self._feats, self._poses, self._bev_aug = self._feats[:B], self._poses[:B], self._bev_aug[:B]
        fresh = self._feats is None or self._feats.shape[0] != B or self._feats.shape[2:] != stored.shape[1:]
        if start is None or fresh:
            start = torch.ones(B, dtype=torch.bool, device=bev.device)
            self._feats = stored.new_zeros(B, T, Cq, X, Y)
            self._poses = pose.new_zeros(B, T, 4, 4)
            self._bev_aug = pose.new_zeros(B, T, 4, 4)
        cur = stored.detach()
        feats, poses, augs = self._feats, self._poses, self._bev_aug
        if bool(start.any()):  # (eager only: the export wrapper always selects)
            s = start.view(B, 1)
            feats = torch.where(s.view(B, 1, 1, 1, 1), cur[:, None].expand_as(feats), feats)
            poses = torch.where(s.view(B, 1, 1, 1), pose[:, None].expand(B, T, 4, 4), poses)
            augs = torch.where(s.view(B, 1, 1, 1), inputs.bev_aug[:, None].expand(B, T, 4, 4), augs)
        # T_curaug_from_prevaug = M_cur inv(T_g_from_cur) T_g_from_prev inv(M_prev), per queued frame
        T_rel = T_curaug_from_prevaug(pose[:, None], inputs.bev_aug[:, None], poses, augs).reshape(B * T, 4, 4)
        history = feats.reshape(B * T, Cq, X, Y)
        if full:  # reduce, then warp: the same values as the cached queue, with gradient into `compress`
            history = self.compress(history)
        warped = warp_bev(history, T_rel, self.grid).view(B, -1, X, Y)
        fused = self.fuse(bev, entry, warped)
        self._feats = torch.cat([cur[:, None], feats[:, :-1]], dim=1)
        self._poses = torch.cat([pose[:, None], poses[:, :-1]], dim=1)
        self._bev_aug = torch.cat([inputs.bev_aug[:, None], augs[:, :-1]], dim=1)
        return fused
