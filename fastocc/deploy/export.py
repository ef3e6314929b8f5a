"""`fastocc export`: a checkpoint -> an ONNX graph for one fixed rig, with a parity check and a JSON sidecar.

The exporter is torch's dynamo-based one (`torch.onnx.export(dynamo=True)`, the default in torch 2.13):
the TorchScript-based exporter refuses `index_add` with repeated indices (LSS pooling), while the dynamo
exporter lowers it to ScatterND(reduction="add"). The file is written only after ONNX Runtime on CPU
reproduces the PyTorch network (the real `FastOcc`, not the export wrapper) within the tolerances.
"""

from __future__ import annotations

import json
import logging
import os
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fastocc.checkpoint import load_model, model_config_to_dict
from fastocc.model import FastOcc
from fastocc.storegrid import check_rig_cameras
from occdata.constants import CLASS_COLORS, CLASS_NAMES
from occdata.fileio import replace_synced, write_atomic
from occdata.sensors.image_ops import IMAGENET_MEAN, IMAGENET_STD

from .predictor import TemporalState
from .rig import DeployError, Rig, load_rig, require_onnx, synthetic_rig
from .sidecar import SIDECAR_FORMAT, sidecar_path
from .static import StaticFastOcc

__all__ = [
    "SIDECAR_FORMAT",
    "ExportConfig",
    "ExportReport",
    "ParityReport",
    "check_parity",
    "custom_domain_ops",
    "export_model",
    "export_onnx",
    "sidecar_path",
]

MIN_OPSET = 18  # the dynamo exporter's lowest; ScatterND(add) needs >= 16, GridSample (temporal warp) >= 16


@dataclass(frozen=True)
class ExportConfig:
    """`rig`: a store or a nuScenes tree (first sample), None for the synthetic rig (the checkpoint's camera
    count and names, nuScenes-like 1600 x 900 cameras). The sidecar records the rig: `camera_order` and
    `rig` (K, extrinsics and each camera's image size). Parity: `frames`
    random frames (temporal models: a stream with ego motion), max |logit diff| <= `max_abs_diff` and
    argmax agreement >= `min_agreement` on every frame."""

    checkpoint: Path
    out: Path
    rig: str | Path | None = None
    opset: int = MIN_OPSET
    frames: int = 2
    max_abs_diff: float = 1e-3
    min_agreement: float = 0.999
    seed: int = 0


@dataclass(frozen=True)
class ParityReport:
    frames: int
    max_abs_diff: float
    min_agreement: float  # worst frame's fraction of voxels with the same argmax
    passed: bool
    limits: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class ExportReport:
    out: Path
    sidecar: Path
    parity: ParityReport
    seconds: float
    size_mib: float
    opset: int
    rig_hash: str


def custom_domain_ops(onnx_path: str | Path) -> list[str]:
    """`domain::op` of every node outside the standard ONNX domain (empty for a portable graph)."""
    import onnx

    model = onnx.load(str(onnx_path), load_external_data=False)
    return sorted({f"{n.domain}::{n.op_type}" for n in model.graph.node if n.domain not in ("", "ai.onnx")})


def _stream_poses(frames: int, seed: int) -> list[np.ndarray]:
    """Ego poses `(4, 4) float64` of a car driving ~1 m per frame with a slight turn, far from the origin."""
    rng = np.random.default_rng(seed)
    poses, T = [], np.eye(4)
    T[:3, 3] = [1234.5, -987.6, 0.3]
    for _ in range(frames):
        poses.append(T.copy())
        step = np.eye(4)
        a = rng.uniform(-0.05, 0.05)
        step[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        step[:2, 3] = [rng.uniform(0.5, 1.5), rng.uniform(-0.1, 0.1)]
        T = T @ step
    return poses


def check_parity(model: FastOcc, static: StaticFastOcc, rig: Rig, session: Any, cfg: ExportConfig) -> ParityReport:
    """ONNX Runtime (`session`) vs the PyTorch network on the same random frames.

    Temporal models run a stream: the first frame starts a sequence, later ones move the ego; the
    network keeps its own queue, the ONNX side gets the queue and T_prev_from_cur as the Predictor does.
    """

    g = torch.Generator().manual_seed(cfg.seed)
    H, W = model.cfg.input_hw
    model.clear_caches()
    state = TemporalState(static.history_shape()) if static.temporal else None
    worst_diff, worst_agree = 0.0, 1.0
    for t, pose in enumerate(_stream_poses(cfg.frames, cfg.seed)):
        images = torch.randn(1, model.cfg.num_cams, 3, H, W, generator=g)
        inputs = rig.scene_inputs(images)
        feeds = {"images": images.numpy()}
        if state is not None:
            feeds.update(state.feeds(pose, seq_start=t == 0))
            origin = state.origin
            rel = torch.as_tensor(np.linalg.inv(origin) @ pose, dtype=torch.float32)[None]
            inputs = type(inputs)(**{**inputs.__dict__, "T_global_from_keyego": rel,
                                     "seq_start": torch.tensor([t == 0])})
        with torch.no_grad():
            ref = model(inputs).voxel_logits.float()
        outs = session.run(None, feeds)
        if state is not None:
            state.push(outs[2], pose)
        logits = torch.from_numpy(outs[0])
        worst_diff = max(worst_diff, float((logits - ref).abs().max()))
        worst_agree = min(worst_agree, float((torch.from_numpy(outs[1]).long() == ref.argmax(1)).double().mean()))
    model.clear_caches()
    passed = worst_diff <= cfg.max_abs_diff and worst_agree >= cfg.min_agreement
    return ParityReport(frames=cfg.frames, max_abs_diff=worst_diff, min_agreement=worst_agree, passed=passed,
                        limits={"max_abs_diff": cfg.max_abs_diff, "min_agreement": cfg.min_agreement})


def _sidecar(static: StaticFastOcc, rig: Rig, parity: ParityReport, opset: int, checkpoint: Path) -> dict[str, Any]:
    cfg = static.cfg
    H, W = cfg.input_hw
    shapes = {"images": [1, cfg.num_cams, 3, H, W]}
    outputs = {"logits": [1, cfg.num_classes, *cfg.fine_grid.shape], "semantics": [1, *cfg.fine_grid.shape]}
    if static.temporal:
        shapes |= {"history": list(static.history_shape()), "T_prev_from_cur": [1, static.history_shape()[1], 4, 4],
                   "seq_start": [1]}
        outputs["history_out"] = list(static.history_shape())
    return {
        "format": SIDECAR_FORMAT,
        "version": 1,
        "opset": opset,
        "inputs": {k: {"shape": v, "dtype": "bool" if k == "seq_start" else "float32"} for k, v in shapes.items()},
        "outputs": {k: {"shape": v, "dtype": "uint8" if k == "semantics" else "float32"} for k, v in outputs.items()},
        "normalisation": {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD), "colour_order": "RGB",
                          "note": "images = (RGB uint8 warped by img_aug - mean) / std, (N, 3, H, W) per camera"},
        "input_hw": [H, W],
        "img_aug": rig.img_aug(cfg.input_hw).tolist(),
        "camera_order": list(rig.cameras),
        "rig": rig.to_json(),
        "rig_hash": rig.hash(cfg.input_hw),
        "class_names": list(CLASS_NAMES),
        "class_colors": [list(c) for c in CLASS_COLORS],
        "temporal": {"num_history": cfg.num_history, "fusion": str(cfg.temporal_fusion),
                     "queue_channels": static.history_shape()[2] if static.temporal else 0,
                     "T_prev_from_cur": "inv(T_global_from_keyego[prev]) @ T_global_from_keyego[cur], nearest "
                                        "first; identity and seq_start=true on a sequence's first frame"},
        "model_config": model_config_to_dict(cfg),
        "checkpoint": str(checkpoint),
        "parity": asdict(parity),
    }


def export_model(model: FastOcc, rig: Rig, cfg: ExportConfig) -> ExportReport:
    """Export a built network (eval mode) for `rig` to `cfg.out` (+ sidecar), parity-checked."""
    require_onnx()
    import onnxruntime as ort

    if Path(cfg.out).suffix.lower() != ".onnx":
        raise DeployError(f"--out {cfg.out} must end in .onnx (the Predictor tells ONNX files by their suffix)")
    if cfg.opset < MIN_OPSET:
        raise DeployError(f"--opset {cfg.opset} is too old: the exporter needs >= {MIN_OPSET}")
    rig.check_cams(model.cfg.num_cams)
    t0 = time.perf_counter()
    model = model.eval()
    static = StaticFastOcc(model, rig).eval()
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp.onnx")
    onnx_log = logging.getLogger("torch.onnx")
    level = onnx_log.level
    try:
        onnx_log.setLevel(logging.ERROR)  # "torchvision is not installed" notices are irrelevant here
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(static, static.example_inputs(cfg.seed), str(tmp), dynamo=True, external_data=False,
                              opset_version=cfg.opset, input_names=static.input_names(),
                              output_names=static.output_names(), verbose=False)
        onnx_log.setLevel(level)
        custom = custom_domain_ops(tmp)
        if custom:
            raise DeployError(f"the exported graph uses non-standard operators {custom}; refusing to write {out}")
        # One thread: ONNX Runtime's threaded ScatterND (the LSS pooling's sum into voxels) adds in a
        # different order on every session, which moved the logits of a real Lyft rig by up to 2.3e-3
        # between sessions of the same file; one thread adds in a fixed order (3.8e-5 from PyTorch there).
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        session = ort.InferenceSession(str(tmp), options, providers=["CPUExecutionProvider"])
        parity = check_parity(model, static, rig, session, cfg)
        if not parity.passed:
            raise DeployError(
                f"parity check failed (max |logit diff| {parity.max_abs_diff:.2e} > {cfg.max_abs_diff:g} or argmax "
                f"agreement {100 * parity.min_agreement:.3f}% < {100 * cfg.min_agreement:g}%); {out} not written")
        replace_synced(tmp, out)  # torch wrote it with open(): the umask's mode
    finally:
        onnx_log.setLevel(level)
        tmp.unlink(missing_ok=True)
    rig_hash = rig.hash(model.cfg.input_hw)
    side = sidecar_path(out)
    write_atomic(side, json.dumps(_sidecar(static, rig, parity, cfg.opset, cfg.checkpoint), indent=1).encode())
    return ExportReport(out=out, sidecar=side, parity=parity, seconds=time.perf_counter() - t0,
                        size_mib=out.stat().st_size / 2**20, opset=cfg.opset, rig_hash=rig_hash)


def export_onnx(cfg: ExportConfig) -> ExportReport:
    """`fastocc export`: load the checkpoint (its own config), load the rig (it must have the checkpoint's
    cameras, in its order: one line naming both rigs if not), export, check, write."""
    model, ckpt = load_model(cfg.checkpoint, "cpu")
    # no --rig: the synthetic ring, with the checkpoint's camera count and names
    rig = load_rig(cfg.rig) if cfg.rig is not None else synthetic_rig(model.cfg.num_cams, ckpt.cameras)
    check_rig_cameras(ckpt.cameras, model.cfg.num_cams, rig.cameras, str(cfg.checkpoint), f"the rig of {rig.source}",
                      "export")
    return export_model(model, rig, cfg)
