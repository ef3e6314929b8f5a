"""`fastocc.Predictor`: streaming inference for a live camera rig, from a checkpoint (PyTorch) or an exported
ONNX file (ONNX Runtime).

    predictor = Predictor("model.onnx")              # or Predictor("ckpt.pt", rig="data.zarr")
    for images, T_global_from_ego in camera_stream:  # N x (h_c, w_c, 3) uint8 RGB in predictor.camera_order
        semantics = predictor(images, T_global_from_ego)   # (200, 200, 16) uint8 class ids

N, the camera order and each camera's image size are the rig's (for an ONNX file: `model.json`'s
`camera_order` and `rig.image_size`); cameras may differ in size, each is resized from its own.

Preprocessing is the loader's own test transform (`fastocc.data.sample.warp_normalise` with
`sample_image_aug(train=False)`), so a deployed model sees exactly what evaluation sees.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fastocc.data.sample import warp_normalise
from fastocc.model.inputs import SceneInputs
from fastocc.storegrid import check_rig_cameras
from occdata.sensors.image_ops import IMAGENET_MEAN, IMAGENET_STD, normalise_lut

from .rig import DeployError, Rig, load_rig, require_onnx, synthetic_rig
from .sidecar import read_sidecar

__all__ = ["Predictor", "StageTimes", "TemporalState"]


class TemporalState:
    """The ONNX graph's queue, kept by the runtime: history `(1, T, C, X, Y) float32` and the ego poses
    `(4, 4) float64` of the queued frames (nearest first). Size is fixed: per-frame cost does not grow."""

    def __init__(self, history_shape: tuple[int, ...]) -> None:
        self.history = np.zeros(history_shape, dtype=np.float32)
        self.T = history_shape[1]
        self.poses: list[np.ndarray] = []
        self.origin: np.ndarray | None = None

    def feeds(self, pose: np.ndarray, seq_start: bool) -> dict[str, np.ndarray]:
        """Graph inputs for the frame at `pose`; a sequence start fills the queue with this frame."""
        if seq_start or self.origin is None:
            self.origin = pose
            self.poses = [pose] * self.T
            self.history[...] = 0.0
            seq_start = True
        rel = np.stack([np.linalg.inv(p) @ pose for p in self.poses])  # float64, then float32: small numbers
        return {"history": self.history, "T_prev_from_cur": rel[None].astype(np.float32),
                "seq_start": np.array([seq_start])}

    def push(self, history_out: np.ndarray, pose: np.ndarray) -> None:
        self.history = history_out
        self.poses = [pose, *self.poses[:-1]]


@dataclass
class StageTimes:
    """Seconds of the last call: preprocessing (warp + normalise) and network (+ argmax / softmax)."""

    preprocess: float = 0.0
    network: float = 0.0


class _TorchBackend:
    def __init__(self, model: torch.nn.Module, rig: Rig, device: str) -> None:
        self.model, self.rig, self.device = model, rig, torch.device(device)
        self.cfg = model.cfg
        self.origin: np.ndarray | None = None

    def reset(self) -> None:
        self.model.clear_caches()
        self.origin = None

    @torch.no_grad()
    def run(self, images: np.ndarray, pose: np.ndarray, seq_start: bool, with_probs: bool
            ) -> tuple[np.ndarray, np.ndarray | None]:
        if seq_start or self.origin is None:
            self.origin, seq_start = pose, True
        x = torch.from_numpy(images).to(self.device)
        inputs = self.rig.scene_inputs(x)
        # poses relative to the sequence's first frame keep float32 exact for the queue's relative motion
        rel = torch.as_tensor(np.linalg.inv(self.origin) @ pose, dtype=torch.float32, device=self.device)[None]
        inputs = SceneInputs(**{**inputs.__dict__, "T_global_from_keyego": rel,
                                "seq_start": torch.tensor([seq_start], device=self.device)})
        logits = self.model(inputs).voxel_logits[0].float()
        semantics = logits.argmax(0).to(torch.uint8).cpu().numpy()
        probs = logits.softmax(0).cpu().numpy() if with_probs else None
        return semantics, probs


class _StaticTorchBackend:
    """The export wrapper (`StaticFastOcc`) run by PyTorch, optionally through `torch.compile`; the queue is
    kept outside the network exactly as for ONNX Runtime."""

    def __init__(self, model: torch.nn.Module, rig: Rig, device: str, compile: bool) -> None:
        from .static import StaticFastOcc

        self.device = torch.device(device)
        self.static = StaticFastOcc(model, rig).eval().to(self.device)
        self.fn = torch.compile(self.static) if compile else self.static
        self.history_shape = self.static.history_shape() if self.static.temporal else None
        self.reset()

    def reset(self) -> None:
        self.state = TemporalState(self.history_shape) if self.history_shape is not None else None

    @torch.no_grad()
    def run(self, images: np.ndarray, pose: np.ndarray, seq_start: bool, with_probs: bool
            ) -> tuple[np.ndarray, np.ndarray | None]:
        args = [torch.from_numpy(images).to(self.device)]
        if self.state is not None:
            args += [torch.from_numpy(v).to(self.device) for v in self.state.feeds(pose, seq_start).values()]
        outs = self.fn(*args)
        if self.state is not None:
            self.state.push(outs[2].cpu().numpy(), pose)
        probs = outs[0][0].float().softmax(0).cpu().numpy() if with_probs else None
        return outs[1][0].cpu().numpy(), probs


class _OnnxBackend:
    def __init__(self, path: Path, meta: dict[str, Any], threads: int | None, providers: Sequence[str] | None) -> None:
        require_onnx()
        import onnxruntime as ort

        opts = ort.SessionOptions()
        if threads is not None:
            opts.intra_op_num_threads = threads
        self.session = ort.InferenceSession(str(path), opts, providers=list(providers or ["CPUExecutionProvider"]))
        hist = meta["inputs"].get("history")
        self.state = TemporalState(tuple(hist["shape"])) if hist else None
        self.history_shape = tuple(hist["shape"]) if hist else None

    def reset(self) -> None:
        if self.history_shape is not None:
            self.state = TemporalState(self.history_shape)

    def run(self, images: np.ndarray, pose: np.ndarray, seq_start: bool, with_probs: bool
            ) -> tuple[np.ndarray, np.ndarray | None]:
        feeds = {"images": images}
        if self.state is not None:
            feeds |= self.state.feeds(pose, seq_start)
        names = ["logits", "semantics", "history_out"] if self.state is not None else ["logits", "semantics"]
        if not with_probs:
            names[0:1] = []
        outs = dict(zip(names, self.session.run(names, feeds), strict=True))
        if self.state is not None:
            self.state.push(outs["history_out"], pose)
        probs = None
        if with_probs:
            logits = torch.from_numpy(outs["logits"][0])
            probs = logits.softmax(0).numpy()
        return outs["semantics"][0], probs


_Backend = _TorchBackend | _StaticTorchBackend | _OnnxBackend


RIGID_ATOL = 1e-4  # |R^T R - I| and |det R - 1| allowed (float32 round trips stay far below it)


def check_rigid_pose(ego_pose: object, name: str = "ego_pose") -> np.ndarray:
    """`ego_pose` as a `(4, 4) float64` rigid transform, or one `DeployError` line saying what is wrong:
    not finite, not 4 x 4, last row not (0, 0, 0, 1), rotation not orthonormal or a reflection (det -1)."""
    try:
        pose = np.asarray(ego_pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise DeployError(f"{name} must be a (4, 4) matrix of numbers, got {type(ego_pose).__name__}") from None
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise DeployError(f"{name} must be a finite (4, 4) matrix (T_global_from_ego), got shape {pose.shape}"
                          + ("" if pose.shape != (4, 4) else " with NaN or inf"))
    if not np.allclose(pose[3], (0.0, 0.0, 0.0, 1.0), atol=RIGID_ATOL):
        raise DeployError(f"{name} is not a rigid transform: its last row is {pose[3].tolist()}, not [0, 0, 0, 1]")
    R = pose[:3, :3]
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if ortho > RIGID_ATOL or abs(det - 1.0) > RIGID_ATOL:
        raise DeployError(f"{name} is not a rigid transform: its rotation is not orthonormal with det +1 "
                          f"(max |R^T R - I| = {ortho:.3g}, det = {det:.4g}; scaled, sheared or mirrored?)")
    return pose


def _default_rig(num_cams: int, cameras: tuple[str, ...] | None = None) -> Rig:
    """The synthetic rig, said out loud: predictions are only meaningful for the rig the images come from."""
    rig = synthetic_rig(num_cams, cameras)
    w, h = (int(v) for v in rig.image_size[0])
    warnings.warn(f"Predictor: no rig given, using the default synthetic nuScenes-like rig ({num_cams} cameras, "
                  f"{w}x{h} images, fixed K and extrinsics); pass rig= a store or nuScenes tree for real cameras",
                  UserWarning, stacklevel=3)
    return rig


class Predictor:
    """Streaming occupancy prediction for a fixed rig, one call per frame.

    `source`: a fastocc checkpoint (run with PyTorch on `device`) or an exported `.onnx` file with its
    `.json` sidecar (run with ONNX Runtime; CPU unless `providers` says otherwise). `rig`: for a
    checkpoint, the rig (a `Rig`, a store or a nuScenes tree; None = the synthetic rig, with a warning
    saying so); for an ONNX file the rig is baked in and a given rig must match it. Images are RGB
    unless `bgr` (OpenCV order). `ego_pose` must be rigid (`check_rigid_pose`).
    """

    def __init__(self, source: str | Path, rig: Rig | str | Path | None = None, device: str = "cpu",
                 threads: int | None = None, bgr: bool = False, providers: Sequence[str] | None = None) -> None:
        path = Path(source)
        if not path.is_file():
            raise DeployError(f"{path}: no such checkpoint or ONNX file")
        self.bgr = bgr
        self.times = StageTimes()
        if path.suffix.lower() == ".onnx":
            meta = read_sidecar(path)
            self.rig = Rig.from_json(meta["rig"])
            self.input_hw = (int(meta["input_hw"][0]), int(meta["input_hw"][1]))
            if rig is not None:
                given = rig if isinstance(rig, Rig) else load_rig(rig)
                if given.num_cams != self.rig.num_cams or given.hash(self.input_hw) != meta["rig_hash"]:
                    raise DeployError(f"{path} was exported for another rig ({self.rig.source}); re-export it "
                                      f"with --rig for {given.source}")
            if (tuple(meta["normalisation"]["mean"]), tuple(meta["normalisation"]["std"])) != (
                    IMAGENET_MEAN, IMAGENET_STD):
                raise DeployError(f"{path}: sidecar normalisation differs from this fastocc's")
            self.num_history = int(meta["temporal"]["num_history"])
            self.class_names = tuple(meta["class_names"])
            self.runtime = "onnx"
            self._backend: _Backend = _OnnxBackend(path, meta, threads, providers)
        else:
            from fastocc.checkpoint import load_model

            if threads is not None:
                torch.set_num_threads(threads)
            model, ckpt = load_model(path, device)
            self.rig = rig if isinstance(rig, Rig) else (
                _default_rig(model.cfg.num_cams, ckpt.cameras) if rig is None else load_rig(rig))
            check_rig_cameras(ckpt.cameras, model.cfg.num_cams, self.rig.cameras, str(path),
                              f"the rig of {self.rig.source}", "Predictor")
            self.rig.check_cams(model.cfg.num_cams)
            self.input_hw = model.cfg.input_hw
            self.num_history = model.cfg.num_history
            from occdata.constants import CLASS_NAMES

            self.class_names = CLASS_NAMES
            self.runtime = "torch"
            self._backend = _TorchBackend(model, self.rig, device)
        self.img_aug = self.rig.img_aug(self.input_hw)
        self.lut = normalise_lut()
        self._frames = 0

    @classmethod
    def from_model(cls, model: torch.nn.Module, rig: Rig | None = None, runtime: str = "torch", device: str = "cpu",
                   bgr: bool = False) -> Predictor:
        """A Predictor around a built `FastOcc` (eval mode). `runtime`: "torch" (the network itself, eager),
        "static" (the export wrapper, eager) or "compile" (the export wrapper through `torch.compile`)."""
        self = cls.__new__(cls)
        self.bgr, self.times, self._frames = bgr, StageTimes(), 0
        self.rig = rig if rig is not None else _default_rig(model.cfg.num_cams)
        self.rig.check_cams(model.cfg.num_cams)
        self.input_hw, self.num_history = model.cfg.input_hw, model.cfg.num_history
        from occdata.constants import CLASS_NAMES

        self.class_names = CLASS_NAMES
        model = model.eval().to(device)
        if runtime == "torch":
            self._backend = _TorchBackend(model, self.rig, device)
        elif runtime in ("static", "compile"):
            self._backend = _StaticTorchBackend(model, self.rig, device, compile=runtime == "compile")
        else:
            raise DeployError(f"unknown runtime {runtime!r}; choose torch, static or compile")
        self.runtime = runtime
        self.img_aug = self.rig.img_aug(self.input_hw)
        self.lut = normalise_lut()
        return self

    @property
    def camera_order(self) -> tuple[str, ...]:
        return self.rig.cameras

    def reset(self) -> None:
        """Start a new sequence on the next call (empties the temporal queue)."""
        self._backend.reset()
        self._frames = 0

    def preprocess(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """N raw camera images `(h_c, w_c, 3) uint8` (camera c at its own calibrated size, in
        `camera_order`) -> network input `(1, N, 3, H, W) float32` through the loader's test transform
        (`warp_normalise`). Wrong count, size or dtype: DeployError."""
        N = self.rig.num_cams
        if isinstance(images, np.ndarray) and images.ndim == 4:
            images = list(images)
        if not isinstance(images, Sequence) or len(images) != N:
            got = len(images) if isinstance(images, Sequence) else type(images).__name__
            raise DeployError(f"expected {N} camera images in the order {list(self.rig.cameras)}, got {got}")
        H, W = self.input_hw
        out = np.empty((1, N, 3, H, W), dtype=np.float32)
        for c, img in enumerate(images):
            ow, oh = (int(v) for v in self.rig.image_size[c])
            if not isinstance(img, np.ndarray) or img.dtype != np.uint8:
                raise DeployError(f"camera {c} ({self.rig.cameras[c]}): images must be uint8 arrays, got "
                                  f"{getattr(img, 'dtype', type(img).__name__)}")
            if img.shape != (oh, ow, 3):
                raise DeployError(f"camera {c} ({self.rig.cameras[c]}): expected a ({oh}, {ow}, 3) image as "
                                  f"calibrated, got {img.shape}")
            warp_normalise(np.ascontiguousarray(img), self.img_aug[c], ow, oh, self.lut, out[0, c], bgr=self.bgr)
        return out

    def __call__(self, images: Sequence[np.ndarray], ego_pose: np.ndarray | None = None, *,
                 seq_start: bool = False, with_probs: bool = False
                 ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """One frame: `images` as for `preprocess`, `ego_pose` T_global_from_ego `(4, 4)` (needed by
        temporal models; ignored otherwise). Returns semantics `(200, 200, 16) uint8`, and with
        `with_probs` also the class probabilities `(18, 200, 200, 16) float32`."""
        if ego_pose is None:
            if self.num_history > 0:
                raise DeployError("this model fuses past frames: pass ego_pose (T_global_from_ego, 4 x 4)")
            pose = np.eye(4)
        else:
            pose = check_rigid_pose(ego_pose)
        t0 = time.perf_counter()
        x = self.preprocess(images)
        t1 = time.perf_counter()
        semantics, probs = self._backend.run(x, pose, seq_start or self._frames == 0, with_probs)
        self.times = StageTimes(preprocess=t1 - t0, network=time.perf_counter() - t1)
        self._frames += 1
        return (semantics, probs) if with_probs else semantics  # type: ignore[return-value]
