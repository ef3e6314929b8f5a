"""The recurrent temporal fusion: one state warped by ego motion and updated by a gated cell per frame."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import REPO

from benchmarks.ablations import ROWS
from fastocc.model import FastOcc
from fastocc.model.config import COARSE_GRID, TEMPORAL_CHANNELS, ModelConfig, TemporalFusionKind, preset
from fastocc.model.inputs import SceneInputs
from fastocc.model.recurrent import RecurrentFusion
from fastocc.model.temporal import T_curaug_from_prevaug, TemporalFusion, warp_bev
from fastocc.train.config import ConfigError, TrainConfig, config_from_dict, incompatible_fields


def _frames(n: int, batch: int = 1, seed: int = 0, channels: int = 8) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(bev (B, C, 100, 100), pose (B, 4, 4)) per frame: the car moves ~1.5 m and turns a little per frame."""
    g = torch.Generator().manual_seed(seed)
    out, pose = [], torch.eye(4)
    pose[:3, 3] = torch.tensor([120.0, -40.0, 0.0])
    for _ in range(n):
        out.append((torch.randn(batch, channels, 100, 100, generator=g), pose.expand(batch, 4, 4).clone()))
        step = torch.eye(4)
        step[:2, :2] = torch.tensor([[math.cos(0.04), -math.sin(0.04)], [math.sin(0.04), math.cos(0.04)]])
        step[0, 3] = 1.5
        pose = pose @ step
    return out


def _inputs(pose: torch.Tensor, start: list[bool], aug: torch.Tensor | None = None) -> SceneInputs:
    B = pose.shape[0]
    z = torch.zeros(B, 1, dtype=pose.dtype)
    aug = torch.eye(4, dtype=pose.dtype).expand(B, 4, 4) if aug is None else aug
    return SceneInputs(z, z, z, z, aug, pose, torch.tensor(start))


def _fusion(unroll: int = 4, state_channels: int = 4, seed: int = 0) -> RecurrentFusion:
    torch.manual_seed(seed)
    fusion = RecurrentFusion(channels=8, grid=COARSE_GRID, state_channels=state_channels, unroll=unroll)
    with torch.no_grad():  # larger weights than the default init: the gates and the state move visibly
        for p in fusion.parameters():
            p.mul_(3.0)
    return fusion


def _conv1x1(x: torch.Tensor, conv: torch.nn.Conv2d) -> torch.Tensor:
    return torch.einsum("oi,bixy->boxy", conv.weight[:, :, 0, 0], x) + conv.bias.view(1, -1, 1, 1)


@torch.no_grad()
def test_recurrent_fusion_equals_the_gru_written_out() -> None:
    """Reference: h_0 = 0; z, r = sigmoid(W_g [x, h]); n = tanh(W_n [x, r h]); h' = (1 - z) h + z n, with
    x = W_c bev and h the previous state warped by the ego motion; out = bev + W_e h'. In float64: in
    float32 the two orders of the same products differed by up to 1.2e-4 in 1 run of 15."""
    fusion = _fusion().double().eval()
    h, prev_pose = None, None
    eye = torch.eye(4, dtype=torch.float64)[None]
    for t, (bev, pose) in enumerate(_frames(5)):
        bev, pose = bev.double(), pose.double()
        out = fusion(bev, _inputs(pose, [t == 0], aug=eye))
        x = _conv1x1(bev, fusion.compress)
        if h is None:
            h = torch.zeros_like(x)
        else:
            h = warp_bev(h, torch.linalg.inv(pose) @ prev_pose, COARSE_GRID)
        z, r = torch.sigmoid(_conv1x1(torch.cat([x, h], 1), fusion.gates)).split(4, dim=1)
        n = torch.tanh(_conv1x1(torch.cat([x, r * h], 1), fusion.candidate))
        h = (1 - z) * h + z * n
        prev_pose = pose
        torch.testing.assert_close(out, bev + _conv1x1(h, fusion.expand), atol=1e-5, rtol=1e-5)


@torch.no_grad()
def test_the_state_carries_a_cell_along_the_ego_motion_by_hand() -> None:
    """C = C_s = 1; z = r = 1 (bias 50), n = tanh(x + h), expand = identity. Frame 0 has a hot cell at
    (60, 50), centre (8.4, 0.4) m, so the state is tanh(1) there. The car then moves 1.6 m forward, twice,
    with empty frames: the output is tanh(tanh(1)) at (58, 50), then tanh(tanh(tanh(1))) at (56, 50),
    and nothing anywhere else."""
    fusion = RecurrentFusion(channels=1, grid=COARSE_GRID, state_channels=1, unroll=1).eval()
    for conv, w, b in ((fusion.compress, [[1.0]], [0.0]), (fusion.gates, [[0.0, 0.0], [0.0, 0.0]], [50.0, 50.0]),
                       (fusion.candidate, [[1.0, 1.0]], [0.0]), (fusion.expand, [[1.0]], [0.0])):
        conv.weight.copy_(torch.tensor(w).view_as(conv.weight))
        conv.bias.copy_(torch.tensor(b))
    bev = torch.zeros(1, 1, 100, 100)
    bev[0, 0, 60, 50] = 1.0
    pose = torch.eye(4)[None]
    fusion(bev, _inputs(pose, [True]))
    t1 = math.tanh(math.tanh(1.0))
    for k, (cell, value) in enumerate((((58, 50), t1), ((56, 50), math.tanh(t1)))):
        pose = pose.clone()
        pose[0, 0, 3] = 1.6 * (k + 1)
        out = fusion(torch.zeros(1, 1, 100, 100), _inputs(pose, [False]))
        assert torch.nonzero(out[0, 0].abs() > 1e-4).tolist() == [list(cell)]
        assert float(out[0, 0, cell[0], cell[1]]) == pytest.approx(value, abs=1e-4)


def test_training_unrolls_the_window_with_gradient_and_the_same_values() -> None:
    """Training recomputes the last `unroll` frames with gradient: with fixed weights the outputs equal
    inference's (carried state, no window), previous frames' maps get no gradient, and the cell's
    gradient depends on the window (unroll 4 differs from unroll 1 from the second frame on). In float64:
    the window's recomputation runs other kernels than the carried state's."""
    frames = [(bev.double(), pose.double()) for bev, pose in _frames(6)]
    outs, grads = {}, {}
    for mode, unroll in (("eval", 4), ("train1", 1), ("train4", 4)):
        fusion = _fusion(unroll=unroll).double()
        fusion.train(mode != "eval")
        for t, (bev, pose) in enumerate(frames):
            bev = bev.clone().requires_grad_(True)
            out = fusion(bev, _inputs(pose, [t == 0]))
            outs.setdefault(mode, []).append(out.detach())
            fusion.zero_grad()
            out.square().mean().backward()
            grads.setdefault(mode, []).append(fusion.gates.weight.grad.clone())
        win = fusion._s["win_bev"]
        assert win.shape[1] == (unroll - 1 if mode != "eval" else 0) and not win.requires_grad
    for mode in ("train1", "train4"):
        for a, b in zip(outs["eval"], outs[mode], strict=True):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(grads["train1"][0], grads["train4"][0])  # frame 0: no history yet
    assert not torch.allclose(grads["train1"][-1], grads["train4"][-1], atol=1e-7)


@torch.no_grad()
def test_seq_start_zeroes_one_lane_and_a_shrinking_batch_keeps_its_first_rows() -> None:
    """In float64: batches of 2 and of 1 take different float32 kernels (2.3e-5 apart on an AMD EPYC,
    against a 1e-5 bound), so the lanes are compared where the kernels' rounding cannot reach the bound."""
    frames = [(bev.double(), pose.double()) for bev, pose in _frames(4, batch=2)]
    a = _fusion(unroll=3).double().train()
    for t, (bev, pose) in enumerate(frames[:3]):
        a(bev, _inputs(pose, [t == 0, t == 0]))
    bev, pose = frames[3]
    out = a(bev, _inputs(pose, [False, True]))
    fresh = _fusion(unroll=3).double().train()(bev[1:], _inputs(pose[1:], [True]))
    torch.testing.assert_close(out[1:], fresh)  # lane 1 restarted: as if it had never seen a frame
    b = _fusion(unroll=3).double().train()
    for t, (bev, pose) in enumerate(frames[:3]):
        b(bev, _inputs(pose, [t == 0, t == 0]))
    bev, pose = frames[3]
    torch.testing.assert_close(b(bev[:1], _inputs(pose[:1], [False])), out[:1])  # lane 0 kept its state
    restarted = _fusion(unroll=3).double().train()(bev[:1], _inputs(pose[:1], [True]))
    assert (out[:1] - restarted).abs().max() > 1e-2  # control: lane 0's history does change its output


@torch.no_grad()
def test_state_round_trips_and_keeps_its_size_whatever_the_stream_length() -> None:
    frames = _frames(12)
    fusion = _fusion(unroll=3).train()
    sizes = set()
    for t, (bev, pose) in enumerate(frames[:8]):
        fusion(bev, _inputs(pose, [t == 0]))
        sizes.add(tuple((k, tuple(v.shape)) for k, v in fusion._s.items()) if t >= 2 else None)
    assert len(sizes - {None}) == 1  # from the window's fill on, the state never grows
    saved = fusion.queue_state()
    copy = _fusion(unroll=3).train()
    copy.load_queue_state(saved)
    for bev, pose in frames[8:]:
        torch.testing.assert_close(copy(bev, _inputs(pose, [False])), fusion(bev, _inputs(pose, [False])))
    with pytest.raises(ValueError, match="not a recurrent"):
        copy.load_queue_state((torch.zeros(1), torch.zeros(1), torch.zeros(1)))  # a queue's state


def test_the_bev_augmentation_is_undone_before_the_state_is_warped() -> None:
    """A frame flipped by the BEV augmentation sees the previous state in its own flipped frame: the warp
    uses M_cur inv(T_cur) T_prev inv(M_prev), as the queue does."""
    fusion = _fusion(unroll=1).eval()
    (b0, p0), (b1, p1) = _frames(2)
    flip = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))[None]
    with torch.no_grad():
        fusion(b0, _inputs(p0, [True]))
        h0 = fusion._s["state"]
        out = fusion(b1, _inputs(p1, [False], aug=flip))
        warped = warp_bev(h0, T_curaug_from_prevaug(p1, flip, p0, torch.eye(4)[None]), COARSE_GRID)
        torch.testing.assert_close(out, fusion.output(b1, fusion.cell(b1, warped)))


def test_config_validates_the_recurrent_fusion() -> None:
    cfg = preset("nano", num_history=16, temporal_fusion="recurrent", temporal_channels=32, temporal_unroll=3)
    assert cfg.temporal_fusion == "recurrent" and cfg.temporal_unroll == 3
    with pytest.raises(ValueError, match="temporal_unroll"):
        ModelConfig(temporal_fusion="recurrent", num_history=1, temporal_unroll=0)
    with pytest.raises(ValueError, match="zero_history_fusion"):
        ModelConfig(temporal_fusion="recurrent", zero_history_fusion=True)


def test_each_fusion_defaults_to_the_width_it_was_measured_at() -> None:
    """The widths behind docs/ablations.md and docs/benchmarks-model.md (docs/results/bench_temporal.json:
    cached16 at the run's C_r, recurrent at its own C_s; the trained `hist16rec` row) are the defaults of
    the config, of TrainConfig and of both modules: none of them can drift from the others."""
    run = json.loads((REPO / "docs/results/bench_temporal.json").read_text())["config"]
    measured = {TemporalFusionKind.CACHED: run["temporal_channels"],
                TemporalFusionKind.RECURRENT: run["rows"]["recurrent"]["temporal_channels"]}
    assert dict(ROWS["hist16rec"].overrides)["temporal_channels"] == measured[TemporalFusionKind.RECURRENT]
    assert TEMPORAL_CHANNELS == measured
    for kind, width in measured.items():
        assert FastOcc(preset("nano", num_history=2, temporal_fusion=kind)).temporal.queue_channels == width
        assert TrainConfig(num_history=2, temporal_fusion=str(kind)).model_config().temporal_width == width
    assert RecurrentFusion(8, COARSE_GRID).queue_channels == measured[TemporalFusionKind.RECURRENT]
    cached = TemporalFusion(8, 2, COARSE_GRID, TemporalFusionKind.CACHED)
    assert cached.queue_channels == measured[TemporalFusionKind.CACHED]
    assert preset("nano", temporal_fusion="recurrent", temporal_channels=8).temporal_width == 8  # given: kept


def test_a_run_saved_with_the_old_explicit_default_resumes_only_where_the_network_is_the_same() -> None:
    """Runs saved before the per-fusion default stored `temporal_channels = 16`: a concat or cached run
    builds the same network with the default now and resumes; a recurrent one would get 32 channels."""
    old = {**TrainConfig().to_dict(), "temporal_channels": 16}
    assert incompatible_fields(old, TrainConfig()) == []
    assert incompatible_fields({**old, "temporal_fusion": "cached"}, TrainConfig(temporal_fusion="cached")) == []
    recurrent = TrainConfig(num_history=16, temporal_fusion="recurrent")
    assert incompatible_fields({**old, **recurrent.to_dict(), "temporal_channels": 16}, recurrent) == [
        "temporal_channels"]
    assert config_from_dict({"temporal_channels": 24}).temporal_channels == 24
    for bad in ("16", True, 1.5):
        with pytest.raises(ConfigError, match="temporal_channels"):
            config_from_dict({"temporal_channels": bad})
