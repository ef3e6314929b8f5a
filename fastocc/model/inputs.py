"""The network's input and output contracts (frozen dataclasses of tensors), and a synthetic camera rig."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["ModelOutputs", "SceneInputs", "synthetic_inputs"]


@dataclass(frozen=True)
class SceneInputs:
    """One batch as the data loader produces it.

    images: `(B, N, 3, H_in, W_in) float32` normalised RGB (N cameras in the store's
        `camera_order`; nuScenes: 6, docs/design.md#frames-and-names order).
    K: `(B, N, 3, 3) float32` intrinsics of each camera's ORIGINAL image (1600 x 900 for nuScenes; cameras
       may differ in size).
    T_keyego_from_cam: `(B, N, 4, 4) float32` camera (x right, y down, z forward) -> key ego.
    img_aug: `(B, N, 3, 3) float32` A: original pixel (u, v, 1) -> augmented (network-input) pixel.
    bev_aug: `(B, 4, 4) float32` M: key ego -> augmented key ego (the labels' frame).
    T_global_from_keyego: `(B, 4, 4) float32` ego pose of this frame (temporal fusion only).
    seq_start: `(B,) bool` True where a new sequence starts (temporal queue reset).
    """

    images: Tensor
    K: Tensor
    T_keyego_from_cam: Tensor
    img_aug: Tensor
    bev_aug: Tensor
    T_global_from_keyego: Tensor | None = None
    seq_start: Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.images.shape[0]

    @property
    def num_cams(self) -> int:
        return self.images.shape[1]

    def to(self, device: torch.device | str) -> SceneInputs:
        moved = {
            f.name: (None if getattr(self, f.name) is None else getattr(self, f.name).to(device))
            for f in dataclasses.fields(self)
        }
        return SceneInputs(**moved)


@dataclass(frozen=True)
class ModelOutputs:
    """What the network returns.

    voxel_logits: `(B, 18, 200, 200, 16) float32` class logits on the fine grid (augmented frame).
    depth_probs: `(B*N, 88, H_in/16, W_in/16) float32` softmax over depth bins (probabilities, not logits);
        None for the attention view transform (no depth net, no depth loss).
    bev_logits: `(B, 18, 200, 200) float32` multi-hot BEV logits, channel c = class c with FREE (17)
        kept as a channel (the paper's M includes empty); None in eval mode or for the baseline heads.
    """

    voxel_logits: Tensor
    depth_probs: Tensor | None
    bev_logits: Tensor | None = None


def _yaw(deg: float) -> Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# camera axes in a forward-looking ego frame: cam x (right) = -y_ego, cam y (down) = -z_ego, cam z = +x_ego
R_EGO_FROM_CAM_FORWARD = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def synthetic_inputs(
    batch: int, input_hw: tuple[int, int], num_cams: int = 6, seed: int = 0, device: str = "cpu"
) -> SceneInputs:
    """A nuScenes-like camera ring (1600 x 900; up to 6 cameras at nuScenes' yaws 60/0/-60/120/180/-120 deg,
    more evenly spaced from 0 deg) with test-time image augmentation (resize to W_in, bottom crop),
    identity BEV augmentation and random images."""
    g = torch.Generator().manual_seed(seed)
    H, W = input_hw
    nuscenes_yaws = (60.0, 0.0, -60.0, 120.0, 180.0, -120.0)
    yaws = nuscenes_yaws[:num_cams] if num_cams <= 6 else tuple(360.0 * n / num_cams for n in range(num_cams))
    T = torch.zeros(num_cams, 4, 4)
    for n, yaw in enumerate(yaws):
        R = _yaw(yaw)
        T[n, :3, :3] = R @ R_EGO_FROM_CAM_FORWARD
        T[n, :3, 3] = R @ torch.tensor([1.0, 0.0, 0.0]) + torch.tensor([1.0, 0.0, 1.6])
        T[n, 3, 3] = 1.0
    K = torch.tensor([[1260.0, 0.0, 800.0], [0.0, 1260.0, 450.0], [0.0, 0.0, 1.0]])
    s = W / 1600.0
    A = torch.tensor([[s, 0.0, 0.0], [0.0, s, H - 900.0 * s], [0.0, 0.0, 1.0]])
    return SceneInputs(
        images=torch.randn(batch, num_cams, 3, H, W, generator=g),
        K=K.expand(batch, num_cams, 3, 3).clone(),
        T_keyego_from_cam=T.expand(batch, num_cams, 4, 4).clone(),
        img_aug=A.expand(batch, num_cams, 3, 3).clone(),
        bev_aug=torch.eye(4).expand(batch, 4, 4).clone(),
        T_global_from_keyego=torch.eye(4).expand(batch, 4, 4).clone(),
        seq_start=torch.ones(batch, dtype=torch.bool),
    ).to(device)
