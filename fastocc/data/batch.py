"""The training batch: model inputs (the `SceneInputs` contract) plus targets, and collation."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:
    from fastocc.model.inputs import SceneInputs

__all__ = ["IGNORE_LABEL", "Batch", "collate"]

IGNORE_LABEL = 255  # semantics where a sample has no labels (test split)


@dataclass(frozen=True)
class Batch:
    """One batch; B samples, N cameras (the store's C, in its `camera_order`), input (H, W), depth grid
    (h, w) = (H // 16, W // 16).

    Inputs (same meaning as `fastocc.model.inputs.SceneInputs`):
      images              (B, N, 3, H, W) float32  normalised RGB (docs/design.md#augmentation mean/std)
      K                   (B, N, 3, 3) float32     ORIGINAL-image intrinsics
      T_keyego_from_cam   (B, N, 4, 4) float32     camera -> key ego
      img_aug             (B, N, 3, 3) float32     A: original pixel (u, v, 1) -> augmented pixel
      bev_aug             (B, 4, 4) float32        M: key ego -> augmented key ego
      T_global_from_keyego (B, 4, 4) float32       key ego -> global
      seq_start           (B,) bool                True where a temporal sequence (re)starts
    Targets (in the augmented BEV frame):
      semantics           (B, 200, 200, 16) int64  labels 0..17 (17 free), 255 = ignore / no labels
      mask_camera, mask_lidar (B, 200, 200, 16) bool
      bev_target          (B, 18, 200, 200) float32 multi-hot per column, channel 17 = free
      depth_target        (B, N, h, w) float32     min LiDAR depth per 16x16 patch, 0 = none
      has_labels          (B,) bool                False: targets above are ignore-filled
    Bookkeeping / temporal:
      sample_index        (B,) int64               store index
      prev_index          (B, 16) int64            store indices of the 16 previous keyframes, nearest first
      prev_valid          (B, 16) bool             False where padded or the frame is not loadable
      T_cur_from_prev     (B, 16, 4, 4) float32    inv(T_global_from_keyego[cur]) @ T_global_from_keyego[prev]
    """

    images: torch.Tensor
    K: torch.Tensor
    T_keyego_from_cam: torch.Tensor
    img_aug: torch.Tensor
    bev_aug: torch.Tensor
    T_global_from_keyego: torch.Tensor
    seq_start: torch.Tensor
    semantics: torch.Tensor
    mask_camera: torch.Tensor
    mask_lidar: torch.Tensor
    bev_target: torch.Tensor
    depth_target: torch.Tensor
    has_labels: torch.Tensor
    sample_index: torch.Tensor
    prev_index: torch.Tensor
    prev_valid: torch.Tensor
    T_cur_from_prev: torch.Tensor

    def __len__(self) -> int:
        return int(self.sample_index.shape[0])

    def _map(self, fn: Any) -> Batch:
        return replace(self, **{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    def to(self, device: torch.device | str, non_blocking: bool = False) -> Batch:
        return self._map(lambda t: t.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> Batch:
        """Called by DataLoader(pin_memory=True) on custom batch types."""
        return self._map(lambda t: t.pin_memory())

    def inputs(self) -> SceneInputs:
        """The model's input record (imported lazily: fastocc.model depends on nothing here)."""
        from fastocc.model.inputs import SceneInputs

        return SceneInputs(
            images=self.images, K=self.K, T_keyego_from_cam=self.T_keyego_from_cam, img_aug=self.img_aug,
            bev_aug=self.bev_aug, T_global_from_keyego=self.T_global_from_keyego, seq_start=self.seq_start,
        )


# Per-sample numpy arrays -> batch dtype. Samples carry compact dtypes (uint8 labels) and are widened here.
_DTYPES: dict[str, np.dtype] = {
    "images": np.dtype(np.float32), "K": np.dtype(np.float32), "T_keyego_from_cam": np.dtype(np.float32),
    "img_aug": np.dtype(np.float32), "bev_aug": np.dtype(np.float32),
    "T_global_from_keyego": np.dtype(np.float32), "seq_start": np.dtype(bool),
    "semantics": np.dtype(np.int64), "mask_camera": np.dtype(bool), "mask_lidar": np.dtype(bool),
    "bev_target": np.dtype(np.float32), "depth_target": np.dtype(np.float32), "has_labels": np.dtype(bool),
    "sample_index": np.dtype(np.int64), "prev_index": np.dtype(np.int64), "prev_valid": np.dtype(bool),
    "T_cur_from_prev": np.dtype(np.float32),
}


def collate(samples: Sequence[dict[str, np.ndarray]]) -> Batch:
    """Stack per-sample dicts (keys = Batch field names, no batch axis) into a Batch."""
    if not samples:
        raise ValueError("collate needs at least one sample")
    out = {}
    for name, dtype in _DTYPES.items():
        arr = np.stack([np.asarray(s[name]) for s in samples])
        out[name] = torch.from_numpy(arr.astype(dtype, copy=False))
    return Batch(**out)
