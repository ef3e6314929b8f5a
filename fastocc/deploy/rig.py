"""A fixed camera rig for deployment: intrinsics, extrinsics, image sizes and the test image transform.

A car runs one rig, so everything the network's geometry depends on (K, T_keyego_from_cam, the test
resize/crop A, identity BEV augmentation) is fixed; `fastocc export` bakes it into the graph and
`fastocc.Predictor` checks images against it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fastocc.data.augment import ImageAugConfig, sample_image_aug
from fastocc.model.inputs import SceneInputs, synthetic_inputs
from occdata.constants import CAMERA_ORDER
from occdata.errors import OccDataError

__all__ = ["DeployError", "Rig", "eval_image_aug", "load_rig", "require_onnx", "synthetic_rig"]


class DeployError(OccDataError):
    """A user-facing deployment problem (bad checkpoint, rig, ONNX file or input images): one line."""


def require_onnx() -> None:
    """ONNX export and ONNX Runtime are an optional extra: say how to get them instead of a traceback."""
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError as exc:
        raise DeployError(f"{exc.name} is not installed: pip install 'fastocc[export]' (onnx, onnxruntime, "
                          "onnxscript)") from None


def eval_image_aug(input_hw: tuple[int, int], orig_w: int, orig_h: int) -> np.ndarray:
    """The loader's test transform A `(3, 3) float64` (resize to the input width, bottom crop): the same
    `sample_image_aug(train=False)` call the loader makes, so deployment and evaluation cannot drift."""
    H, W = input_hw
    return sample_image_aug(ImageAugConfig(height=H, width=W, train=False), orig_w, orig_h, None).matrix


@dataclass(frozen=True, eq=False)
class Rig:
    """N cameras in model order. K `(N, 3, 3) float64` of each camera's original image, T_keyego_from_cam
    `(N, 4, 4) float64`, image_size `(N, 2) int64` as (width, height) per camera (cameras may differ),
    camera names, and where it came from."""

    K: np.ndarray
    T_keyego_from_cam: np.ndarray
    image_size: np.ndarray
    cameras: tuple[str, ...]
    source: str

    @property
    def num_cams(self) -> int:
        return len(self.cameras)

    def img_aug(self, input_hw: tuple[int, int]) -> np.ndarray:
        """A per camera `(N, 3, 3) float64` for the network input size (the test transform)."""
        return np.stack([eval_image_aug(input_hw, int(w), int(h)) for w, h in self.image_size])

    def hash(self, input_hw: tuple[int, int]) -> str:
        """sha256 over everything the baked geometry depends on (float32 values as the graph sees them)."""
        h = hashlib.sha256()
        for arr in (self.K, self.T_keyego_from_cam, self.img_aug(input_hw)):
            h.update(np.ascontiguousarray(arr, dtype=np.float32).tobytes())
        h.update(np.ascontiguousarray(self.image_size, dtype=np.int64).tobytes())
        h.update(repr((tuple(input_hw), self.cameras)).encode())
        return h.hexdigest()

    def scene_inputs(self, images: torch.Tensor) -> SceneInputs:
        """SceneInputs for `images (B, N, 3, H, W)` on this rig: test transform, identity BEV augmentation."""
        B, N, _, H, W = images.shape
        self.check_cams(N)

        def rep(a: np.ndarray) -> torch.Tensor:
            t = torch.as_tensor(np.asarray(a, dtype=np.float32), device=images.device)
            return t.expand(B, *t.shape).clone()

        return SceneInputs(
            images=images,
            K=rep(self.K),
            T_keyego_from_cam=rep(self.T_keyego_from_cam),
            img_aug=rep(self.img_aug((H, W))),
            bev_aug=rep(np.eye(4)),
            T_global_from_keyego=rep(np.eye(4)),
            seq_start=torch.ones(B, dtype=torch.bool, device=images.device),
        )

    def check_cams(self, num_cams: int) -> None:
        if num_cams != self.num_cams:
            raise DeployError(f"the rig ({self.source}) has {self.num_cams} cameras but the model expects "
                              f"{num_cams}")

    def to_json(self) -> dict:
        return {"cameras": list(self.cameras), "source": self.source, "K": self.K.tolist(),
                "T_keyego_from_cam": self.T_keyego_from_cam.tolist(), "image_size": self.image_size.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> Rig:
        return cls(K=np.asarray(d["K"], dtype=np.float64),
                   T_keyego_from_cam=np.asarray(d["T_keyego_from_cam"], dtype=np.float64),
                   image_size=np.asarray(d["image_size"], dtype=np.int64), cameras=tuple(d["cameras"]),
                   source=str(d["source"]))


def synthetic_rig(num_cams: int = 6, cameras: tuple[str, ...] | None = None) -> Rig:
    """`fastocc.model.synthetic_inputs`'s nuScenes-like ring: 1600 x 900 images, K and extrinsics as there.
    `cameras`: their names (default nuScenes' order, then CAM_6, CAM_7, ... beyond 6)."""
    if cameras is None:
        cameras = (CAMERA_ORDER + tuple(f"CAM_{n}" for n in range(len(CAMERA_ORDER), num_cams)))[:num_cams]
    if len(cameras) != num_cams:
        raise DeployError(f"synthetic rig: {len(cameras)} camera names for {num_cams} cameras")
    inp = synthetic_inputs(1, (128, 352), num_cams)
    return Rig(K=inp.K[0].double().numpy(), T_keyego_from_cam=inp.T_keyego_from_cam[0].double().numpy(),
               image_size=np.tile(np.array([1600, 900], dtype=np.int64), (num_cams, 1)),
               cameras=tuple(cameras), source="synthetic")


def _rig_from_store(path: Path) -> Rig:
    from occdata.store.layout import STATE_DONE, store_rig
    from occdata.store.reader import open_store

    reader = open_store(path)
    done = np.flatnonzero(reader.small("status/state") == STATE_DONE)
    if done.size == 0:
        raise DeployError(f"store {path} has no built sample to take the rig from")
    i = int(done[0])
    cams = tuple(store_rig(reader.attrs)["cameras"])
    return Rig(K=np.asarray(reader.small("calib/K")[i], dtype=np.float64),
               T_keyego_from_cam=np.asarray(reader.small("calib/T_keyego_from_cam")[i], dtype=np.float64),
               image_size=np.asarray(reader.small("cam/image_size")[i], dtype=np.int64), cameras=cams,
               source=f"store {path} sample {i} ({reader.token(i)})")


def _rig_from_nuscenes(path: Path) -> Rig:
    from occdata.nuscenes.reader import load_nuscenes

    ds = load_nuscenes(path)
    if not ds.samples:
        raise DeployError(f"nuScenes tree {path} has no sample to take the rig from")
    s = ds.samples[0]
    cams = s.camera_rig()
    return Rig(K=cams.K.astype(np.float64), T_keyego_from_cam=cams.T_keyego_from_cam, image_size=cams.image_size,
               cameras=cams.channels, source=f"nuScenes {path} sample {s.token}")


def load_rig(source: str | Path | None) -> Rig:
    """The rig of a store's first built sample, of a nuScenes tree's first sample, or (None) the synthetic one."""
    if source is None:
        return synthetic_rig()
    path = Path(source)
    if not path.exists():
        raise DeployError(f"rig source {path} does not exist (give a store or a nuScenes tree)")
    if (path / "zarr.json").is_file() or (path / ".zgroup").is_file():
        return _rig_from_store(path)
    return _rig_from_nuscenes(path)
