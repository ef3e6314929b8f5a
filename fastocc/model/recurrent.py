"""Recurrent temporal fusion: one BEV state carried forward, warped by ego motion (docs/model.md).

Per frame, whatever the length of the stream: reduce the current BEV map, warp the previous state into
the current frame, one gated update (a ConvGRU cell with 1x1 convolutions), one residual expansion.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from occdata.constants import OccGrid

from .config import TEMPORAL_CHANNELS, TemporalFusionKind
from .inputs import SceneInputs
from .temporal import T_curaug_from_prevaug, warp_bev, warp_bev_inverse

__all__ = ["RecurrentFusion"]

_STATE_KEYS = ("state", "pose", "aug", "win_bev", "win_pose", "win_aug", "win_valid")


class RecurrentFusion(nn.Module):
    """fused = bev + expand(h_t), h_t = GRU(x_t = compress(bev_t), warp(h_{t-1})).

    The cell: z, r = sigmoid(gates([x, h])); n = tanh(candidate([x, r h])); h_t = h + z (n - h); all
    1x1 convolutions on `state_channels` (C_s) channels, so a frame costs the same whether the stream
    is 2 or 2000 frames long. The warp aligns the previous state with the current augmented key ego
    (the queue's transform, `T_curaug_from_prevaug`); the BEV encoder after the fusion gives the
    spatial context. No normalisation in the recurrence: a state is the same function of the weights
    in training and at inference.

    The state is zero at a sequence start (`seq_start`, the first call, a batch of another shape); a
    batch smaller than the last keeps the first rows (lanes that ended were the last rows).

    Training (truncated back-propagation through time over `unroll` frames): the module keeps the
    full BEV maps of the last `unroll - 1` frames (detached) and the state before them; each step
    recomputes the recurrence over that window with gradient, so the cell learns from up to `unroll`
    frames of history while the state carries everything since the sequence start. At inference the
    window is empty (`unroll` 1): one cell step per frame.
    """

    def __init__(self, channels: int, grid: OccGrid,
                 state_channels: int = TEMPORAL_CHANNELS[TemporalFusionKind.RECURRENT], unroll: int = 4) -> None:
        super().__init__()
        self.grid = grid
        self.unroll = unroll
        c_s = state_channels
        self.queue_channels = c_s
        self.queue_length = 1  # the ONNX graph's history: the one state
        self.compress = nn.Conv2d(channels, c_s, 1)
        self.gates = nn.Conv2d(2 * c_s, 2 * c_s, 1)
        self.candidate = nn.Conv2d(2 * c_s, c_s, 1)
        self.expand = nn.Conv2d(c_s, channels, 1)
        self._s: dict[str, Tensor] | None = None

    # -- the cell --------------------------------------------------------------------------------------
    def cell(self, bev: Tensor, h_warped: Tensor) -> Tensor:
        """One update: current map `(B, C, X, Y)`, previous state warped into its frame `(B, C_s, X, Y)`
        -> the new state `(B, C_s, X, Y)`."""
        x = self.compress(bev)
        z, r = torch.sigmoid(self.gates(torch.cat([x, h_warped], dim=1))).chunk(2, dim=1)
        n = torch.tanh(self.candidate(torch.cat([x, r * h_warped], dim=1)))
        return h_warped + z * (n - h_warped)

    def output(self, bev: Tensor, h: Tensor) -> Tensor:
        return bev + self.expand(h)

    def static_step(self, bev: Tensor, history: Tensor, T_prev_from_cur: Tensor, seq_start: Tensor
                    ) -> tuple[Tensor, Tensor]:
        """The export graph's step: bev `(1, C, X, Y)`, history `(1, 1, C_s, X, Y)` (the state),
        T_prev_from_cur `(1, 1, 4, 4)`, seq_start `(1,)` -> fused `(1, C, X, Y)`, next history."""
        h = torch.where(seq_start.view(1, 1, 1, 1), torch.zeros_like(history[:, 0]), history[:, 0])
        h = self.cell(bev, warp_bev_inverse(h, T_prev_from_cur[:, 0], self.grid))
        return self.output(bev, h), h.unsqueeze(1)

    # -- streaming state -------------------------------------------------------------------------------
    def reset(self) -> None:
        self._s = None

    def queue_state(self) -> dict[str, Tensor] | None:
        """The state and the training window, detached on the CPU (None when empty); `load_queue_state`
        restores it exactly (checkpoints, validation)."""
        return None if self._s is None else {k: v.detach().cpu() for k, v in self._s.items()}

    def load_queue_state(self, state: dict[str, Tensor] | None, device: torch.device | str | None = None) -> None:
        if state is None:
            self.reset()
            return
        if not isinstance(state, dict) or set(state) != set(_STATE_KEYS):
            raise ValueError("the saved temporal state is not a recurrent fusion's (another temporal_fusion?)")
        dev = device if device is not None else next(self.parameters()).device
        self._s = {k: v.to(dev) for k, v in state.items()}

    def _begin(self, bev: Tensor, pose: Tensor, aug: Tensor, start: Tensor | None) -> dict[str, Tensor]:
        """The state for this batch: rows of ended lanes dropped, zeroed where a sequence starts."""
        B, C, X, Y = bev.shape
        s = self._s
        if s is not None and s["state"].shape[0] > B and start is not None:
            s = {k: v[:B] for k, v in s.items()}
        if s is None or s["state"].shape[0] != B or s["win_bev"].shape[2] != C or start is None:
            z4 = pose.new_zeros(B, 0, 4, 4)
            s = {"state": bev.new_zeros(B, self.queue_channels, X, Y), "pose": pose, "aug": aug,
                 "win_bev": bev.new_zeros(B, 0, C, X, Y), "win_pose": z4, "win_aug": z4,
                 "win_valid": torch.zeros(B, 0, dtype=torch.bool, device=bev.device)}
            start = torch.ones(B, dtype=torch.bool, device=bev.device)
        if bool(start.any()):
            b, m = start.view(B, 1, 1, 1), start.view(B, 1, 1)
            s = {**s, "state": torch.where(b, 0.0, s["state"]), "pose": torch.where(m, pose, s["pose"]),
                 "aug": torch.where(m, aug, s["aug"]), "win_valid": s["win_valid"] & ~start.view(B, 1)}
        return s

    def _step(self, bev: Tensor, h: Tensor, h_pose: Tensor, h_aug: Tensor, pose: Tensor, aug: Tensor) -> Tensor:
        return self.cell(bev, warp_bev(h, T_curaug_from_prevaug(pose, aug, h_pose, h_aug), self.grid))

    def forward(self, bev: Tensor, inputs: SceneInputs) -> Tensor:
        """bev `(B, C, X, Y)` in the current augmented frame -> fused `(B, C, X, Y)`."""
        B = bev.shape[0]
        pose = inputs.T_global_from_keyego
        if pose is None:
            pose = torch.eye(4, device=bev.device).expand(B, 4, 4)
        aug = inputs.bev_aug
        s = self._begin(bev, pose, aug, inputs.seq_start)
        h, h_pose, h_aug = s["state"], s["pose"], s["aug"]
        trail = []  # (state, pose, aug) after each window frame, then after this one
        for i in range(s["win_bev"].shape[1]):  # training: recompute the window with gradient
            ok = s["win_valid"][:, i]
            p_i, a_i = s["win_pose"][:, i], s["win_aug"][:, i]
            h_i = self._step(s["win_bev"][:, i], h, h_pose, h_aug, p_i, a_i)
            h = torch.where(ok.view(B, 1, 1, 1), h_i, h)
            h_pose = torch.where(ok.view(B, 1, 1), p_i, h_pose)
            h_aug = torch.where(ok.view(B, 1, 1), a_i, h_aug)
            trail.append((h, h_pose, h_aug))
        h_new = self._step(bev, h, h_pose, h_aug, pose, aug)
        trail.append((h_new, pose, aug))
        self._advance(s, bev, pose, aug, trail)
        return self.output(bev, h_new)

    def _advance(self, s: dict[str, Tensor], bev: Tensor, pose: Tensor, aug: Tensor,
                 trail: list[tuple[Tensor, Tensor, Tensor]]) -> None:
        """Keep this frame. The window holds the last `unroll - 1` frames in training, none otherwise:
        the frames that leave it (the oldest one, or this one at inference) hand on the state after
        them (`trail`, one entry per window frame and this one), detached."""
        window = self.unroll - 1 if self.training else 0
        n_old = s["win_bev"].shape[1]
        drop = max(0, n_old + 1 - window)  # frames leaving the window, this one last
        state, st_pose, st_aug = (s["state"], s["pose"], s["aug"]) if drop == 0 else trail[drop - 1]
        win = {k: s[f"win_{k}"][:, drop:] for k in ("bev", "pose", "aug", "valid")}
        if drop <= n_old:  # this frame stays in the window (no copy of its map at inference)
            new = {"bev": bev.detach(), "pose": pose, "aug": aug,
                   "valid": torch.ones(bev.shape[0], dtype=torch.bool, device=bev.device)}
            win = {k: torch.cat([v, new[k][:, None]], dim=1) for k, v in win.items()}
        self._s = {"state": state.detach(), "pose": st_pose, "aug": st_aug,
                   **{f"win_{k}": v for k, v in win.items()}}
