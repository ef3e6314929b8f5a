"""The CPU interpolation-sampling kernels: numba against their numpy twins, and the sampler's CPU path
against the torch `embedding_bag` path (an independent implementation), values and gradients."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from reference.model_sampling_kernels import bag_backward_numpy, bag_forward_numpy, bilinear_pairs_numpy

from fastocc.model.inputs import synthetic_inputs
from fastocc.model.interp import InterpolationSampler
from fastocc.model.sampling_kernels import bag_backward, bag_forward, bilinear_pairs
from occdata.constants import GRID

HW, STRIDE = (96, 256), 16
FEAT_HW = (HW[0] // STRIDE, HW[1] // STRIDE)


def _augmented_inputs(batch: int = 2):
    """The synthetic rig with a different image scale/shift per camera and a BEV flip + rotation."""
    x = synthetic_inputs(batch, HW, seed=1)
    g = torch.Generator().manual_seed(5)
    img_aug = x.img_aug.clone()
    img_aug[..., 0, 0] *= 1 + 0.1 * torch.rand(img_aug.shape[:2], generator=g)
    img_aug[..., 1, 1] *= 1 + 0.1 * torch.rand(img_aug.shape[:2], generator=g)
    img_aug[..., :2, 2] += 5 * torch.randn(*img_aug.shape[:2], 2, generator=g)
    c, s = np.cos(0.3), np.sin(0.3)
    bev = torch.tensor([[-c, -s, 0, 0], [s, -c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float32)
    bev_aug = torch.stack([torch.eye(4), bev])[:batch]
    return type(x)(**{**x.__dict__, "img_aug": img_aug, "bev_aug": bev_aug})


def _one_camera_set(inputs, b: int):
    T = torch.linalg.inv(inputs.bev_aug[:, None] @ inputs.T_keyego_from_cam)[b, :, :3, :].numpy()
    return T, (inputs.img_aug @ inputs.K)[b].numpy()


def test_pairs_kernel_equals_its_numpy_twin():
    inputs = _augmented_inputs()
    rng = np.random.default_rng(0)
    points = rng.uniform([-40, -40, -1], [40, 40, 5.4], size=(20_000, 3)).astype(np.float32)
    cam, proj = _one_camera_set(inputs, 1)
    got = bilinear_pairs(points, cam, proj, HW, STRIDE, FEAT_HW, row0=96)
    ref = bilinear_pairs_numpy(points, cam, proj, HW, STRIDE, FEAT_HW, row0=96)
    np.testing.assert_array_equal(got[0], ref[0])
    assert got[0][-1] > 5_000  # many pairs, some voxels in two cameras
    assert np.diff(got[0]).max() == 2
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_allclose(got[2], ref[2], rtol=0, atol=2e-6)
    # each seen voxel's weights sum to 1 away from the map border
    sums = np.add.reduceat(got[2].sum(1), got[0][:-1][np.diff(got[0]) > 0])
    assert abs(float(np.median(sums)) - 1) < 1e-6


def test_bag_kernels_equal_their_numpy_twins():
    """Exactly, whatever the order of the sums (the kernels' threads and chunks, numpy's add.at): weights
    in steps of 1/8 and values in steps of 1/16 make every product and partial sum a float32 number."""
    rng = np.random.default_rng(1)
    counts = rng.integers(0, 3, size=500)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    E, n_rows, C = int(offsets[-1]), 40, 5
    rows = rng.integers(0, n_rows, size=(E, 4)).astype(np.int64)
    weights = (rng.integers(1, 9, size=(E, 4)) / 8).astype(np.float32)
    weights[rng.random((E, 4)) < 0.2] = 0
    table = (rng.integers(-48, 49, size=(n_rows, C)) / 16).astype(np.float32)
    grad = (rng.integers(-48, 49, size=(500, C)) / 16).astype(np.float32)
    np.testing.assert_array_equal(bag_forward(table, offsets, rows, weights),
                                  bag_forward_numpy(table, offsets, rows, weights))
    for chunks in (1, 2, 3):
        np.testing.assert_array_equal(bag_backward(grad, offsets, rows, weights, n_rows, chunks),
                                      bag_backward_numpy(grad, offsets, rows, weights, n_rows))
    assert np.abs(bag_backward_numpy(grad, offsets, rows, weights, n_rows)).max() > 1  # not all zeros


def test_cpu_sampler_equals_the_embedding_bag_path_values_and_gradients():
    inputs = _augmented_inputs()
    sampler = InterpolationSampler(GRID, HW, STRIDE)
    g = torch.Generator().manual_seed(2)
    feat = torch.randn(2 * 6, 7, *FEAT_HW, generator=g, requires_grad=True)
    upstream = torch.randn(2, *GRID.shape, 7, generator=g)

    out = sampler(feat, inputs)  # CPU float32: the numba kernels
    (out * upstream).sum().backward()
    got_grad = feat.grad.clone()
    feat.grad = None

    index = sampler.index(inputs, FEAT_HW)  # the torch path's own index and embedding_bag
    table = feat.permute(0, 2, 3, 1).reshape(-1, 7)
    ref = F.embedding_bag(index.rows, table, index.offsets, mode="sum", per_sample_weights=index.weights)
    ref = ref.view(2, *GRID.shape, 7)
    (ref * upstream).sum().backward()

    seen = ref.abs().sum(-1) > 0
    assert int(seen.sum()) > 100_000
    # float32 projections in another order may flip a voxel that sits on an image border: allow 1e-4
    close = torch.isclose(out, ref, rtol=1e-4, atol=1e-5).all(-1)
    assert float(close.float().mean()) > 1 - 1e-4
    assert float((out - ref).detach().abs()[close].max()) < 1e-4
    rel = float((got_grad - feat.grad).abs().max() / feat.grad.abs().max())
    assert rel < 1e-3


def test_cpu_sampler_index_is_cached_while_the_rig_stays():
    inputs = _augmented_inputs(1)
    sampler = InterpolationSampler(GRID, HW, STRIDE)
    first = sampler.pair_index(inputs, FEAT_HW)
    assert sampler.pair_index(inputs, FEAT_HW) is first
    moved = type(inputs)(**{**inputs.__dict__, "bev_aug": torch.eye(4)[None] * 1.0})
    moved.bev_aug[0, 0, 3] = 0.5
    assert sampler.pair_index(moved, FEAT_HW) is not first
