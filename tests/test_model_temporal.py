"""The temporal queue warps previous BEV features by ego motion (and BEV augmentation) and resets on seq_start."""

from __future__ import annotations

import math

import pytest
import torch

from fastocc.model.config import COARSE_GRID
from fastocc.model.inputs import SceneInputs
from fastocc.model.temporal import TemporalFusion, warp_bev


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
