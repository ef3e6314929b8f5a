"""The temporal queue warps previous BEV features by ego motion (and BEV augmentation) and resets on seq_start."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from fastocc.model.config import COARSE_GRID, TemporalFusionKind
from fastocc.model.inputs import SceneInputs
from fastocc.model.temporal import T_curaug_from_prevaug, TemporalFusion, warp_bev


def _frame(pose: torch.Tensor, bev_aug: torch.Tensor, start: bool) -> SceneInputs:
    z = torch.zeros(1, 1)
    return SceneInputs(
        images=z,
        K=z,
        T_keyego_from_cam=z,
        img_aug=z,
        bev_aug=bev_aug[None],
        T_global_from_keyego=pose[None],
        seq_start=torch.tensor([start]),
    )


def _select_warped(fusion: TemporalFusion, which: int) -> None:
    """Make the reduce layer output the `which`-th queued frame unchanged (identity BN, ReLU of positives)."""
    conv, bn = fusion.reduce[0], fusion.reduce[1]
    with torch.no_grad():
        conv.weight.zero_()
        conv.weight[0, which, 0, 0] = 1.0
    bn.eval()


def test_queue_warps_a_cell_by_the_ego_motion_in_the_augmented_frame() -> None:
    # M = flip x in both frames. Hot cell (60, 50) of the previous frame: augmented centre (8.4, 0.4)
    # -> key ego (-8.4, 0.4) = global (pose identity). The car then moves +1.6 m along x:
    # current key ego (-10.0, 0.4) -> augmented (10.0, 0.4) -> cell ((10 + 40) / 0.8 - 0.5, 50) = (62, 50).
    flip_x = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    moved = torch.eye(4)
    moved[0, 3] = 1.6
    fusion = TemporalFusion(channels=1, num_history=2, grid=COARSE_GRID)
    _select_warped(fusion, 1)  # channel 0 = current, 1 = nearest previous
    prev = torch.zeros(1, 1, 100, 100)
    prev[0, 0, 60, 50] = 1.0
    fusion(prev, _frame(torch.eye(4), flip_x, start=True))
    out = fusion(torch.zeros(1, 1, 100, 100), _frame(moved, flip_x, start=False))
    out = out.detach()
    assert torch.nonzero(out[0, 0] > 1e-3).tolist() == [[62, 50]]  # float32 rounding leaks < 1e-3 to neighbours
    torch.testing.assert_close(out[0, 0, 62, 50], torch.tensor(1.0), atol=1e-3, rtol=0)


def test_warp_under_a_yaw_of_90_degrees() -> None:
    # previous cell (60, 50) = (8.4, 0.4); current pose yawed +90 deg at the same place:
    # p_cur = Rz(-90) p = (0.4, -8.4) -> cell ((0.4 + 40)/0.8 - 0.5, (-8.4 + 40)/0.8 - 0.5) = (50, 39)
    prev = torch.zeros(1, 1, 100, 100)
    prev[0, 0, 60, 50] = 1.0
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    T_global_from_cur = torch.tensor([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    T_cur_from_prev = torch.linalg.inv(T_global_from_cur)
    out = warp_bev(prev, T_cur_from_prev[None], COARSE_GRID)
    assert torch.nonzero(out[0, 0] > 1e-3).tolist() == [[50, 39]]


@torch.no_grad()
def test_seq_start_resets_the_queue_and_history_length_is_capped() -> None:
    fusion = TemporalFusion(channels=1, num_history=2, grid=COARSE_GRID)
    _select_warped(fusion, 2)  # the second-nearest previous frame
    eye = torch.eye(4)
    for t in range(20):  # a long stream: the queue never grows beyond num_history
        fusion(torch.full((1, 1, 100, 100), float(t + 1)), _frame(eye, eye, start=t == 0))
        assert fusion._feats is not None and fusion._feats.shape[1] == 2
    out = fusion(torch.full((1, 1, 100, 100), 50.0), _frame(eye, eye, start=False))
    assert float(out[0, 0, 50, 50]) == pytest.approx(19.0, rel=1e-4)  # two frames back (BN eps)
    out = fusion(torch.full((1, 1, 100, 100), 7.0), _frame(eye, eye, start=True))
    assert float(out[0, 0, 50, 50]) == pytest.approx(7.0, rel=1e-4)  # reset: history filled with the current frame


@torch.no_grad()
def test_seq_start_resets_only_the_flagged_sample_of_a_batch() -> None:
    fusion = TemporalFusion(channels=1, num_history=1, grid=COARSE_GRID)
    _select_warped(fusion, 1)
    eye = torch.eye(4).expand(2, 4, 4)

    def frame(start: list[bool]) -> SceneInputs:
        z = torch.zeros(2, 1)
        return SceneInputs(z, z, z, z, eye, eye, torch.tensor(start))

    fusion(torch.full((2, 1, 100, 100), 3.0), frame([True, True]))
    out = fusion(torch.full((2, 1, 100, 100), 5.0), frame([False, True]))
    assert float(out[0, 0, 50, 50]) == pytest.approx(3.0, rel=1e-4)  # continues: previous frame
    assert float(out[1, 0, 50, 50]) == pytest.approx(5.0, rel=1e-4)  # new sequence: its own frame


@torch.no_grad()
def test_a_shrinking_batch_keeps_the_history_of_its_first_rows() -> None:
    """Lane 1 ended (the exactly-once plan ends lanes from the last slot): lane 0 keeps its history."""
    fusion = TemporalFusion(channels=1, num_history=1, grid=COARSE_GRID)
    _select_warped(fusion, 1)

    def frame(start: list[bool]) -> SceneInputs:
        z, eye = torch.zeros(len(start), 1), torch.eye(4).expand(len(start), 4, 4)
        return SceneInputs(z, z, z, z, eye, eye, torch.tensor(start))

    feats = torch.stack([torch.full((1, 100, 100), 3.0), torch.full((1, 100, 100), 4.0)])
    fusion(feats, frame([True, True]))
    out = fusion(torch.full((1, 1, 100, 100), 5.0), frame([False]))
    assert float(out[0, 0, 50, 50]) == pytest.approx(3.0, rel=1e-4)  # lane 0's previous frame, not a reset


# -- the "cached" fusion: each frame reduced once, when current ------------------------------------------
def _moving_stream(n: int, seed: int = 0) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(bev (1, 8, 100, 100), pose (4, 4)) per frame: the car moves ~1.5 m and turns a little per frame."""
    g = torch.Generator().manual_seed(seed)
    out, pose = [], torch.eye(4)
    pose[:3, 3] = torch.tensor([120.0, -40.0, 0.0])
    for _ in range(n):
        out.append((torch.randn(1, 8, 100, 100, generator=g), pose.clone()))
        a = 0.04
        step = torch.eye(4)
        step[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        step[0, 3] = 1.5
        pose = pose @ step
    return out


def _cached(num_history: int = 3) -> TemporalFusion:
    torch.manual_seed(0)
    fusion = TemporalFusion(channels=8, num_history=num_history, grid=COARSE_GRID, kind=TemporalFusionKind.CACHED,
                            cached_channels=4)
    bn = fusion.mix_norm[0]
    with torch.no_grad():  # non-trivial normalisation statistics, eval mode
        bn.running_mean.uniform_(-0.5, 0.5)
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.uniform_(0.5, 1.5)
        bn.bias.uniform_(-0.2, 0.2)
    return fusion.eval()


@torch.no_grad()
def test_cached_fusion_equals_the_literal_concat_reference() -> None:
    """Reference written out: every frame's reduced map r_t = conv(bev_t); the queue = the T previous r (the
    first frame's r repeated at the sequence start); each warped by M_cur inv(T_g_cur) T_g_prev inv(M_prev);
    ONE conv over the literal concatenation [r_t, warped...]; BN, ReLU, expand, plus the current map. In
    float64: the module's two convs and the reference's one sum the same products in another order."""
    fusion = _cached().double()
    flip_y = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=torch.float64))  # the same M in every frame
    T = fusion.num_history
    w_mix = torch.cat([fusion.mix_current.weight, fusion.mix_history.weight], dim=1)  # the concat conv
    reduced: list[tuple[torch.Tensor, torch.Tensor]] = []
    for t, (bev, pose) in enumerate((b.double(), p.double()) for b, p in _moving_stream(6)):
        out = fusion(bev, _frame(pose, flip_y, start=t == 0))
        r = F.conv2d(bev, fusion.compress.weight, fusion.compress.bias)
        queue = [reduced[max(0, t - k)] for k in range(1, T + 1)] if t > 0 else [(r, pose)] * T
        warped = [warp_bev(r_prev, T_curaug_from_prevaug(pose, flip_y, pose_prev, flip_y)[None], COARSE_GRID)
                  for r_prev, pose_prev in queue]
        mixed = F.relu(fusion.mix_norm[0](F.conv2d(torch.cat([r, *warped], dim=1), w_mix)))
        ref = bev + F.conv2d(mixed, fusion.expand.weight, fusion.expand.bias)
        torch.testing.assert_close(out, ref, atol=1e-4, rtol=1e-4)
        reduced.append((r, pose))
        if t > 0:  # the history matters: a model without it gives something else
            alone = bev + F.conv2d(F.relu(fusion.mix_norm[0](F.conv2d(torch.cat([r, *[r] * T], 1), w_mix))),
                                   fusion.expand.weight, fusion.expand.bias)
            assert float((out - alone).abs().max()) > 1e-2


@torch.no_grad()
def test_cached_fusion_reduces_each_frame_once_and_keeps_only_reduced_maps() -> None:
    fusion = _cached(num_history=16)
    seen: list[torch.Tensor] = []
    fusion.compress.register_forward_hook(lambda m, args, out: seen.append(args[0]))
    stream = _moving_stream(20)
    eye = torch.eye(4)
    for t, (bev, pose) in enumerate(stream):
        fusion(bev, _frame(pose, eye, start=t == 0))
        assert len(seen) == t + 1 and seen[-1] is bev  # once per frame, on the current map only
        assert fusion._feats is not None and fusion._feats.shape == (1, 16, 4, 100, 100)  # C_r, not C
        newest = F.conv2d(bev, fusion.compress.weight, fusion.compress.bias)
        torch.testing.assert_close(fusion._feats[0, 0], newest[0], atol=1e-6, rtol=0)
    oldest = F.conv2d(stream[20 - 16][0], fusion.compress.weight, fusion.compress.bias)
    torch.testing.assert_close(fusion._feats[0, 15], oldest[0], atol=1e-6, rtol=0)


@torch.no_grad()
def test_cached_queue_warps_a_cell_by_the_ego_motion() -> None:
    """The concat test's hot cell, through the cached queue: identity reduce/mix/expand on channel 0."""
    flip_x = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    moved = torch.eye(4)
    moved[0, 3] = 1.6
    fusion = TemporalFusion(channels=1, num_history=2, grid=COARSE_GRID, kind=TemporalFusionKind.CACHED,
                            cached_channels=1).eval()
    for conv in (fusion.compress, fusion.mix_current, fusion.mix_history, fusion.expand):
        conv.weight.zero_()
        if conv.bias is not None:
            conv.bias.zero_()
    fusion.compress.weight[0, 0] = 1.0
    fusion.mix_history.weight[0, 0] = 1.0  # the nearest previous frame (channel 0 of the history)
    fusion.expand.weight[0, 0] = 1.0
    prev = torch.zeros(1, 1, 100, 100)
    prev[0, 0, 60, 50] = 1.0
    fusion(prev, _frame(torch.eye(4), flip_x, start=True))
    out = fusion(torch.zeros(1, 1, 100, 100), _frame(moved, flip_x, start=False))
    assert torch.nonzero(out[0, 0] > 1e-3).tolist() == [[62, 50]]
    torch.testing.assert_close(out[0, 0, 62, 50], torch.tensor(1.0), atol=1e-3, rtol=0)


def test_cached_fusion_trains_every_parameter_and_detaches_the_queue() -> None:
    fusion = _cached().train()
    (bev0, pose0), (bev1, pose1) = _moving_stream(2)
    bev0.requires_grad_(True)
    bev1.requires_grad_(True)
    eye = torch.eye(4)
    fusion(bev0, _frame(pose0, eye, start=True))
    out = fusion(bev1, _frame(pose1, eye, start=False))
    out.square().mean().backward()
    assert bev0.grad is None  # the queued map is detached: no gradient into a previous frame
    assert bev1.grad is not None
    missing = [n for n, p in fusion.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing  # compress learns through the current frame's slot


def test_grad_history_gives_the_cached_values_and_trains_the_reduction_through_the_queue() -> None:
    """temporal_grad_history: the training queue keeps full maps and reduces them with gradient; the
    forward values are the cached queue's (reduce, then warp), so the deployed cache serves the same model.
    In float64: the training queue reduces T maps in one batch, the cache one map at a time."""
    eye = torch.eye(4, dtype=torch.float64)
    stream = [(b.double(), p.double()) for b, p in _moving_stream(4)]
    outs, grads = {}, {}
    for grad_history in (False, True):
        fusion = _cached().double()
        fusion.grad_history = grad_history
        fusion.train()
        compress_grads = []
        for t, (bev, pose) in enumerate(stream):
            out = fusion(bev, _frame(pose, eye, start=t == 0))
            outs.setdefault(grad_history, []).append(out.detach())
            fusion.zero_grad()
            out.square().mean().backward()
            compress_grads.append(fusion.compress.weight.grad.clone())
        grads[grad_history] = compress_grads
        queued = fusion._feats.shape[2]
        assert queued == (8 if grad_history else 4)  # the full map (C) or the reduced one (C_r)
    for a, b in zip(outs[False], outs[True], strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    # frame 0's queue is its own map: only from frame 1 on does the history carry gradient of its own
    assert not torch.allclose(grads[False][-1], grads[True][-1], atol=1e-7)


def test_zero_history_fusion_is_the_history_rows_fusion_layer_without_history() -> None:
    """hist0fuse: the same 1x1 conv + BN + ReLU as the history rows, over the current map alone."""
    from fastocc.model import FastOcc, preset, synthetic_inputs

    cfg = preset("nano", zero_history_fusion=True)
    assert cfg.num_history == 0 and cfg.has_temporal
    torch.manual_seed(0)
    net = FastOcc(cfg).eval()
    hist = FastOcc(preset("nano", num_history=16))
    assert net.temporal is not None and hist.temporal is not None
    names = {n for n, _ in net.temporal.named_parameters()}
    assert names == {n for n, _ in hist.temporal.named_parameters()}  # the same layer, narrower input
    assert net.temporal.reduce[0].weight.shape == (128, 128, 1, 1)
    inputs = synthetic_inputs(1, cfg.input_hw)
    with torch.no_grad():
        feat = net.image_stage(inputs.images)
        _, bev = net.view_stage(feat, inputs)
        from fastocc.model.network import collapse_z

        depth, context = net.depth_net(feat)
        raw = collapse_z(net.pooling(depth, context, inputs))
        ref = F.relu(net.temporal.reduce[1](F.conv2d(raw, net.temporal.reduce[0].weight)))
    torch.testing.assert_close(bev, ref, atol=1e-5, rtol=1e-5)
    assert net.temporal.queue_state() is None  # no queue


def test_old_checkpoints_load_as_concat(tmp_path) -> None:  # noqa: ANN001
    import json

    from fastocc.checkpoint import load_model, model_config_to_dict, save_checkpoint
    from fastocc.model import FastOcc, preset

    cfg = preset("nano", num_history=2)
    path = save_checkpoint(tmp_path / "old.pt", cfg, FastOcc(cfg).state_dict())
    payload = torch.load(path, weights_only=True)
    old = model_config_to_dict(cfg)
    for k in ("temporal_fusion", "temporal_channels", "zero_history_fusion"):
        del old[k]
    payload["model_config"] = json.dumps(old)
    torch.save(payload, path)
    model, ckpt = load_model(path)
    assert ckpt.model_config.temporal_fusion is TemporalFusionKind.CONCAT and hasattr(model.temporal, "reduce")
    cached = preset("nano", num_history=2, temporal_fusion="cached", temporal_channels=8)
    model, ckpt = load_model(save_checkpoint(tmp_path / "new.pt", cached, FastOcc(cached).state_dict()))
    assert ckpt.model_config == cached and model.temporal.queue_channels == 8


def test_train_config_selects_the_fusion() -> None:
    from fastocc.train.config import ConfigError, TrainConfig

    m = TrainConfig(num_history=16, temporal_fusion="cached", temporal_channels=8).model_config()
    assert m.temporal_fusion is TemporalFusionKind.CACHED and m.temporal_channels == 8
    assert TrainConfig().model_config().temporal_fusion is TemporalFusionKind.CONCAT  # not the default yet
    with pytest.raises(ConfigError, match="temporal_fusion"):
        TrainConfig(temporal_fusion="gru")
    assert TrainConfig(num_history=16, temporal_fusion="cached", temporal_grad_history=True).model_config(
    ).temporal_grad_history
    with pytest.raises(ConfigError, match="temporal_grad_history"):
        TrainConfig(num_history=16, temporal_grad_history=True)
