"""Geometry of the view transform and of interpolation sampling, with image and BEV augmentation active.

Hand-built rig: one camera looking along ego +x from (0.2, -0.2, 1.2) m, K = [[1000, 0, 830], [0, 1000, 674]].
Image augmentation A = flip(W=352) @ crop(24, 97) @ resize(0.25): u' = 375 - 0.25 u, v' = 0.25 v - 97,
so the principal point (830, 674) -> augmented (167.5, 71.5) = centre of feature cell (row 4, col 10).
BEV augmentation M = flip y. A second camera looks backwards (yaw 180 deg) and sees none of this.
"""

from __future__ import annotations

import torch

from fastocc.model.config import COARSE_GRID, DEPTH_BINS
from fastocc.model.inputs import R_EGO_FROM_CAM_FORWARD, SceneInputs
from fastocc.model.interp import InterpolationSampler
from fastocc.model.view_transform import LSSPooling, PoolingIndex, lss_pool
from occdata.constants import GRID

H_IN, W_IN = 128, 352


def _rig(second_camera_same: bool = False) -> SceneInputs:
    K = torch.tensor([[1000.0, 0.0, 830.0], [0.0, 1000.0, 674.0], [0.0, 0.0, 1.0]])
    A = torch.tensor([[-0.25, 0.0, 375.0], [0.0, 0.25, -97.0], [0.0, 0.0, 1.0]])
    T0 = torch.eye(4)
    T0[:3, :3] = R_EGO_FROM_CAM_FORWARD
    T0[:3, 3] = torch.tensor([0.2, -0.2, 1.2])
    T1 = T0.clone()
    if not second_camera_same:
        T1[:3, :3] = torch.diag(torch.tensor([-1.0, -1.0, 1.0])) @ R_EGO_FROM_CAM_FORWARD  # yaw 180 deg
    M = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0]))
    return SceneInputs(
        images=torch.zeros(1, 2, 3, H_IN, W_IN),
        K=K.expand(1, 2, 3, 3).clone(),
        T_keyego_from_cam=torch.stack([T0, T1])[None],
        img_aug=A.expand(1, 2, 3, 3).clone(),
        bev_aug=M[None],
    )


def test_painted_pixel_is_pooled_into_the_voxel_on_its_ray_at_the_bin_depth() -> None:
    # bin 20 centre = 1.0 + 0.5 * 20.5 = 11.25 m along the optical axis -> key ego (11.45, -0.2, 1.2)
    # -> flip y (11.45, 0.2, 1.2) -> coarse voxel floor(51.45/0.8, 40.2/0.8, 2.2/0.8) = (64, 50, 2)
    inputs = _rig()
    pooling = LSSPooling(COARSE_GRID, DEPTH_BINS.centres(), (H_IN, W_IN), 16)
    depth = torch.zeros(2, 88, 8, 22)
    depth[0, 20, 4, 10] = 1.0
    context = torch.arange(1.0, 4.0).view(1, 3, 1, 1).expand(2, 3, 8, 22).contiguous()
    volume = pooling(depth, context, inputs)
    assert volume.shape == (1, 3, 100, 100, 8)
    nz = torch.nonzero(volume[0, 0])
    assert nz.tolist() == [[64, 50, 2]]
    assert volume[0, :, 64, 50, 2].tolist() == [1.0, 2.0, 3.0]


def test_pooling_indices_are_cached_until_the_augmentation_changes() -> None:
    inputs = _rig()
    pooling = LSSPooling(COARSE_GRID, DEPTH_BINS.centres(), (H_IN, W_IN), 16)
    first = pooling.index(inputs, (8, 22))
    assert pooling.index(inputs, (8, 22)) is first
    flipped = SceneInputs(**{**inputs.__dict__, "bev_aug": torch.eye(4)[None]})
    assert pooling.index(flipped, (8, 22)) is not first


def test_interpolation_samples_the_feature_the_voxel_centre_projects_to() -> None:
    # voxel (130, 100, 5): centre (12.2, 0.2, 1.2) -> M^-1 (12.2, -0.2, 1.2) -> camera (0, 0, 12)
    # -> pixel (830, 674) -> augmented (167.5, 71.5) -> feature cell (4, 10) exactly.
    # voxel (130, 101, 5): y = 0.6 -> camera x = 0.4 -> u = 830 + 1000 * 0.4 / 12 = 863.33
    # -> u' = 375 - 215.83 = 159.17 -> feature x = (159.17 - 7.5) / 16 = 9.4792: weight 0.4792 on column 10.
    feat = torch.zeros(2, 3, 8, 22)
    feat[0, :, 4, 10] = torch.tensor([1.0, 2.0, 3.0])
    sampler = InterpolationSampler(GRID, (H_IN, W_IN), 16)
    out = sampler(feat, _rig())
    assert out.shape == (1, 200, 200, 16, 3)
    torch.testing.assert_close(out[0, 130, 100, 5], torch.tensor([1.0, 2.0, 3.0]))
    torch.testing.assert_close(out[0, 130, 101, 5], torch.tensor([1.0, 2.0, 3.0]) * (9.47917 - 9), atol=1e-4, rtol=0)
    assert float(out[0, 30, 100, 5].abs().sum()) == 0.0  # x = -27.8 m: behind camera 0, outside camera 1's image
    # the same voxel seen by two cameras (camera 1 identical, its feature map zero): mean -> half
    out2 = InterpolationSampler(GRID, (H_IN, W_IN), 16)(feat, _rig(second_camera_same=True))
    torch.testing.assert_close(out2[0, 130, 100, 5], torch.tensor([0.5, 1.0, 1.5]))


def test_lss_pool_gradient_equals_dense_reference() -> None:
    g = torch.Generator().manual_seed(0)
    BN, D, h, w, C, B, grid_shape = 2, 5, 3, 4, 3, 1, (4, 3, 2)
    n_points, n_vox = BN * D * h * w, 4 * 3 * 2
    point_idx = torch.randperm(n_points, generator=g)[:90]
    voxel_idx = torch.randint(0, n_vox, (90,), generator=g)
    index = PoolingIndex(point_idx=point_idx, voxel_idx=voxel_idx)
    depth = torch.rand(BN, D, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    context = torch.randn(BN, C, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn(B, C, *grid_shape, generator=g, dtype=torch.float64)

    out = lss_pool(depth, context, index, B, grid_shape)
    (out * upstream).sum().backward()
    grads = depth.grad.clone(), context.grad.clone()
    depth.grad = context.grad = None

    S = torch.zeros(n_vox, n_points, dtype=torch.float64)  # dense pooling matrix
    S[voxel_idx, point_idx] = 1.0
    feats = (depth.unsqueeze(-1) * context.permute(0, 2, 3, 1).unsqueeze(1)).reshape(n_points, C)
    ref = (S @ feats).view(B, *grid_shape, C).permute(0, 4, 1, 2, 3)
    (ref * upstream).sum().backward()
    torch.testing.assert_close(out, ref)
    torch.testing.assert_close(grads[0], depth.grad)
    torch.testing.assert_close(grads[1], context.grad)
