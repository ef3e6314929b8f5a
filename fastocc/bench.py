"""Per-stage latency, analytic FLOPs, parameters and peak memory of the network (the paper's table layout).

Stages: image (ResNet + FPN) / view transform (depth net + LSS pooling + temporal fusion) / head (3D side:
FastOcc's BEV decoder + interpolation + fusion + classifier, or a baseline). FLOPs are multiply-accumulates
from the shapes seen in one pass: k^2 C_in C_out H W per 2D conv, k^3 C_in C_out H W Z per 3D conv,
in x out per row for linear layers, plus analytic terms for LSS pooling (N D C2 h w) and interpolation
(4 N C H W Z). Timing: warm-up runs, then the median of `repeats` runs, CUDA synchronised.
"""

from __future__ import annotations

import contextlib
import math
import resource
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn

from .losses import LossConfig, LossTargets, occupancy_loss
from .model import FastOcc, HeadKind, ModelConfig, preset, synthetic_inputs

__all__ = [
    "PAPER_SPLIT_MS",
    "RUNTIMES",
    "BenchConfig",
    "RuntimeBenchConfig",
    "SplitBenchConfig",
    "format_report",
    "format_runtime_report",
    "format_split_report",
    "run_benchmark",
    "run_runtime_benchmark",
    "run_split_benchmark",
]


@dataclass(frozen=True)
class BenchConfig:
    """What to measure. mode "infer": eval + no_grad per stage, geometry caches warm (fixed rig);
    mode "train": forward + combined loss + backward of the whole network, caches cleared every run
    (augmentation changes every batch in training)."""

    preset: str = "nano"
    heads: tuple[HeadKind, ...] = (HeadKind.FASTOCC,)
    device: str = "cpu"
    batch: int = 1
    repeats: int = 5
    warmup: int = 1
    mode: Literal["infer", "train"] = "infer"
    threads: int | None = None
    seed: int = 0
    view_transform: str = "lss"  # lss | attention (the SurroundOcc* view transform)
    input_hw: tuple[int, int] | None = None  # None = the preset's
    num_history: int | None = None  # None = the preset's


def _model_config(cfg: BenchConfig, head: HeadKind) -> ModelConfig:
    extra: dict[str, Any] = {"input_hw": tuple(cfg.input_hw)} if cfg.input_hw else {}
    if cfg.num_history is not None:
        extra["num_history"] = cfg.num_history
    return preset(cfg.preset, head=head, view_transform=cfg.view_transform, **extra)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _median_seconds(fn: Callable[[], Any], cfg: BenchConfig, device: torch.device) -> float:
    for _ in range(cfg.warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(cfg.repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _macs(module: nn.Module, inputs: tuple[Any, ...], output: Any) -> int:
    if isinstance(module, nn.Conv2d | nn.Conv3d):
        k = math.prod(module.kernel_size)
        return k * module.in_channels // module.groups * module.out_channels * output[0, 0].numel() * output.shape[0]
    if isinstance(module, nn.ConvTranspose3d | nn.ConvTranspose2d):
        x = inputs[0]
        k = math.prod(module.kernel_size)
        return k * module.in_channels * module.out_channels // module.groups * x[0, 0].numel() * x.shape[0]
    if isinstance(module, nn.Linear):
        return module.in_features * module.out_features * output.numel() // module.out_features
    return 0


@contextlib.contextmanager
def _count_macs() -> Iterator[list[int]]:
    total = [0]

    def hook(module: nn.Module, inputs: tuple[Any, ...], output: Any) -> None:
        total[0] += _macs(module, inputs, output)

    handle = nn.modules.module.register_module_forward_hook(hook)
    try:
        yield total
    finally:
        handle.remove()


def _params(*modules: nn.Module | None) -> int:
    return sum(p.numel() for m in modules if m is not None for p in m.parameters())


def _peak_mib(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux: process peak RSS


def _reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def _build(model_cfg: ModelConfig, device: torch.device, seed: int) -> FastOcc:
    torch.manual_seed(seed)
    return FastOcc(model_cfg).to(device)


def _bench_infer(cfg: BenchConfig, device: torch.device) -> dict[str, Any]:
    base_cfg = _model_config(cfg, cfg.heads[0])
    inputs = synthetic_inputs(cfg.batch, base_cfg.input_hw, base_cfg.num_cams, cfg.seed, str(device))
    net = _build(base_cfg, device, cfg.seed).eval()
    h, w = base_cfg.feat_hw
    N, B = base_cfg.num_cams, cfg.batch
    X, Y, Z = base_cfg.fine_grid.shape
    result: dict[str, Any] = {"stages": {}, "heads": {}}
    with torch.no_grad():
        _reset_peak(device)
        with _count_macs() as macs:
            feat = net.image_stage(inputs.images)
        t_img = _median_seconds(lambda: net.image_stage(inputs.images), cfg, device)
        result["stages"]["image"] = {
            "ms": 1e3 * t_img,
            "gmacs": macs[0] / 1e9,
            "params": _params(net.backbone, net.neck) - _params(net.backbone.fc),
            "peak_mib": _peak_mib(device),
        }
        _reset_peak(device)
        with _count_macs() as macs:
            _, bev = net.view_stage(feat, inputs)
        if net.temporal is not None:
            net.temporal.reset()
        t_view = _median_seconds(lambda: net.view_stage(feat, inputs), cfg, device)
        if net.attention is None:
            pool_macs = N * B * base_cfg.depth_bins.count * base_cfg.context_channels * h * w
        else:  # bilinear sampling: 4 corners x samples (heads x points) x C2 per voxel and camera
            pool_macs = 4 * N * B * base_cfg.attention_points * base_cfg.context_channels * math.prod(
                base_cfg.coarse_grid.shape)
        result["stages"]["view"] = {
            "ms": 1e3 * t_view,
            "gmacs": (macs[0] + pool_macs) / 1e9,
            "params": _params(net.depth_net, net.attention, net.temporal),
            "peak_mib": _peak_mib(device),
        }
        for head in cfg.heads:
            head_net = net if head is cfg.heads[0] else _build(base_cfg.replace(head=head), device, cfg.seed).eval()
            _reset_peak(device)
            with _count_macs() as macs:
                logits, _ = head_net.head_stage(feat, bev, inputs)
            assert logits.shape == (B, base_cfg.num_classes, X, Y, Z)
            t_head = _median_seconds(lambda hn=head_net: hn.head_stage(feat, bev, inputs), cfg, device)
            interp = 4 * N * B * base_cfg.fuse_channels * X * Y * Z if head is HeadKind.FASTOCC else 0
            result["heads"][head.value] = {
                "ms": 1e3 * t_head,
                "gmacs": (macs[0] + interp) / 1e9,
                "params": _params(head_net.head),
                "peak_mib": _peak_mib(device),
                "total_ms": 1e3 * (t_img + t_view + t_head),
            }
            del head_net
    return result


def _random_targets(model_cfg: ModelConfig, batch: int, device: torch.device) -> LossTargets:
    g = torch.Generator().manual_seed(1)
    X, Y, Z = model_cfg.fine_grid.shape
    h, w = model_cfg.feat_hw
    bins = torch.randint(0, model_cfg.depth_bins.count, (batch * model_cfg.num_cams, h, w), generator=g)
    return LossTargets(
        voxel_labels=torch.randint(0, model_cfg.num_classes, (batch, X, Y, Z), generator=g).to(device),
        mask_camera=(torch.rand(batch, X, Y, Z, generator=g) > 0.5).to(device),
        depth_onehot=F.one_hot(bins, model_cfg.depth_bins.count).permute(0, 3, 1, 2).float().to(device),
        bev_multihot=(torch.rand(batch, model_cfg.num_classes, X, Y, generator=g) > 0.8).float().to(device),
    )


def _train_one(cfg: BenchConfig, head: HeadKind, device: torch.device) -> dict[str, Any]:
    model_cfg = _model_config(cfg, head)
    inputs = synthetic_inputs(cfg.batch, model_cfg.input_hw, model_cfg.num_cams, cfg.seed, str(device))
    targets = _random_targets(model_cfg, cfg.batch, device)
    net = _build(model_cfg, device, cfg.seed).train()

    def step_net_only() -> None:
        net.clear_caches()
        out = net(inputs)
        extra = out.bev_logits.mean() if out.bev_logits is not None else 0.0
        depth = out.depth_probs.mean() if out.depth_probs is not None else 0.0
        (out.voxel_logits.mean() + depth + extra).backward()
        net.zero_grad(set_to_none=True)

    def step() -> None:
        net.clear_caches()
        out = net(inputs)
        total, _ = occupancy_loss(out.voxel_logits, targets, LossConfig(), out.depth_probs, out.bev_logits)
        total.backward()
        net.zero_grad(set_to_none=True)

    _reset_peak(device)
    t_net = _median_seconds(step_net_only, cfg, device)
    t_all = _median_seconds(step, cfg, device)
    return {
        "fwd_bwd_s_per_sample": t_net / cfg.batch,
        "fwd_loss_bwd_s_per_sample": t_all / cfg.batch,
        "params": _params(net) - _params(net.backbone.fc),
        "peak_mib": _peak_mib(device),
    }


def _bench_train(cfg: BenchConfig, device: torch.device) -> dict[str, Any]:
    return {"heads": {head.value: _train_one(cfg, head, device) for head in cfg.heads}}


def run_benchmark(cfg: BenchConfig) -> dict[str, Any]:
    """Run the benchmark described by `cfg`; returns a JSON-ready dict (times in ms or s as named)."""
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but CUDA is not available")
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    run = _bench_infer if cfg.mode == "infer" else _bench_train
    result = run(cfg, device)
    model_cfg = _model_config(cfg, cfg.heads[0])
    result["config"] = {
        "preset": cfg.preset,
        "input_hw": list(model_cfg.input_hw),
        "view_transform": cfg.view_transform,
        "mode": cfg.mode,
        "device": cfg.device,
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "threads": torch.get_num_threads(),
        "batch": cfg.batch,
        "repeats": cfg.repeats,
        "warmup": cfg.warmup,
        "torch": torch.__version__,
        "peak_memory_note": "CUDA: max_memory_allocated per stage; CPU: process peak RSS so far (monotonic)",
    }
    heads = result["heads"]
    if cfg.mode == "infer" and "fastocc" in heads and "3dfcn" in heads:
        result["fastocc_over_3dfcn_head_time"] = heads["fastocc"]["ms"] / heads["3dfcn"]["ms"]
    return result


def format_report(result: dict[str, Any]) -> str:
    """Human-readable table of `run_benchmark`'s result."""
    c = result["config"]
    lines = [f"preset {c['preset']} {c['input_hw']} mode {c['mode']} on {c['device_name']} ({c['threads']} threads)"]
    if c["mode"] == "infer":
        for name, s in result["stages"].items():
            lines.append(
                f"  {name:<8} {s['ms']:9.1f} ms {s['gmacs']:8.2f} GMAC {s['params'] / 1e6:7.2f} M params"
                f"  peak {s['peak_mib']:8.0f} MiB"
            )
        for name, s in result["heads"].items():
            lines.append(
                f"  head {name:<7}{s['ms']:8.1f} ms {s['gmacs']:8.2f} GMAC {s['params'] / 1e6:7.2f} M params"
                f"  peak {s['peak_mib']:8.0f} MiB  total {s['total_ms']:8.1f} ms"
            )
        if "fastocc_over_3dfcn_head_time" in result:
            lines.append(f"  FastOcc head / 3D FCN head time: {result['fastocc_over_3dfcn_head_time']:.3f}")
    else:
        for name, s in result["heads"].items():
            lines.append(
                f"  {name:<8} fwd+bwd {s['fwd_bwd_s_per_sample']:.3f} s/sample, with all losses "
                f"{s['fwd_loss_bwd_s_per_sample']:.3f} s/sample, {s['params'] / 1e6:.2f} M params, "
                f"peak {s['peak_mib']:.0f} MiB"
            )
    return "\n".join(lines)


RUNTIMES: tuple[str, ...] = ("torch", "compile", "onnx")


@dataclass(frozen=True)
class RuntimeBenchConfig:
    """End-to-end latency per frame through `fastocc.Predictor`: 6 raw uint8 1600 x 900 images (synthetic rig)
    -> preprocessing (the loader's test transform) -> network -> (200, 200, 16) uint8 semantics.

    runtimes: "torch" (the network, eager), "compile" (the fixed-rig export wrapper through torch.compile),
    "onnx" (the exported graph in ONNX Runtime, exported here with its parity check)."""

    preset: str = "nano"
    head: HeadKind = HeadKind.FASTOCC
    runtimes: tuple[str, ...] = RUNTIMES
    device: str = "cpu"
    repeats: int = 5
    warmup: int = 2
    threads: int | None = None
    seed: int = 0


def _time_predictor(pred: Any, frames: list, poses: list, warmup: int, repeats: int) -> tuple[Any, dict[str, float]]:
    """The first call's output and seconds, then the medians (ms) of `repeats` timed calls after `warmup`:
    whole frame, preprocessing and network (`Predictor.times`)."""
    t0 = time.perf_counter()
    first = pred(frames[0], poses[0])
    first_call = time.perf_counter() - t0
    for i in range(warmup):
        pred(frames[(i + 1) % 2], poses[(i + 1) % 2])
    totals, pre, netw = [], [], []
    for i in range(repeats):
        t0 = time.perf_counter()
        pred(frames[i % 2], poses[i % 2])
        totals.append(time.perf_counter() - t0)
        pre.append(pred.times.preprocess)
        netw.append(pred.times.network)
    return first, {"ms": 1e3 * statistics.median(totals), "preprocess_ms": 1e3 * statistics.median(pre),
                   "network_ms": 1e3 * statistics.median(netw), "first_call_s": first_call}


def run_runtime_benchmark(cfg: RuntimeBenchConfig) -> dict[str, Any]:
    """Median end-to-end ms per frame and its split (preprocess / network) per runtime, in one process."""
    import tempfile
    from pathlib import Path

    import numpy as np

    from .deploy import ExportConfig, Predictor, export_model, synthetic_rig

    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but CUDA is not available")
    unknown = sorted(set(cfg.runtimes) - set(RUNTIMES))
    if unknown:
        raise ValueError(f"unknown runtime(s) {unknown}; choose from {list(RUNTIMES)}")
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    threads = torch.get_num_threads()
    model_cfg = preset(cfg.preset, head=cfg.head)
    model = _build(model_cfg, torch.device("cpu"), cfg.seed).eval()
    rig = synthetic_rig(model_cfg.num_cams)
    rng = np.random.default_rng(cfg.seed)
    frames = [[rng.integers(0, 256, (int(h), int(w), 3), dtype=np.uint8) for w, h in rig.image_size]
              for _ in range(2)]
    poses = [np.eye(4), np.eye(4)]
    poses[1][0, 3] = 1.0
    result: dict[str, Any] = {"runtimes": {}}
    reference = None
    with tempfile.TemporaryDirectory() as tmp:
        for rt in cfg.runtimes:
            t0 = time.perf_counter()
            if rt == "onnx":
                if device.type != "cpu":
                    raise ValueError("the onnx runtime is benchmarked on CPU only (onnxruntime CPU build)")
                out = Path(tmp) / "model.onnx"
                export_model(model, rig, ExportConfig(checkpoint=Path("(in memory)"), out=out, frames=1))
                pred = Predictor(out, threads=threads)
            else:
                pred = Predictor.from_model(model, rig, runtime=rt, device=cfg.device)
            setup = time.perf_counter() - t0
            first, timing = _time_predictor(pred, frames, poses, cfg.warmup, cfg.repeats)
            if reference is None:
                reference = first
            result["runtimes"][rt] = {**timing, "setup_s": setup,
                                      "argmax_agreement_percent": 100.0 * float((first == reference).mean())}
            del pred
    rts = result["runtimes"]
    if "torch" in rts:
        for r in rts.values():
            r["ratio_to_torch"] = r["ms"] / rts["torch"]["ms"]
    result["config"] = {
        "preset": cfg.preset,
        "head": cfg.head.value,
        "input_hw": list(model_cfg.input_hw),
        "device": cfg.device,
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "threads": threads,
        "repeats": cfg.repeats,
        "warmup": cfg.warmup,
        "torch": torch.__version__,
        "image_size": [int(v) for v in rig.image_size[0]],
    }
    return result


def format_runtime_report(result: dict[str, Any]) -> str:
    c = result["config"]
    lines = [f"preset {c['preset']} head {c['head']} {c['input_hw']} end-to-end per frame on {c['device_name']} "
             f"({c['threads']} threads), raw {c['image_size'][0]}x{c['image_size'][1]} images"]
    for rt, r in result["runtimes"].items():
        ratio = f"  x{r['ratio_to_torch']:.2f} of torch" if "ratio_to_torch" in r else ""
        lines.append(f"  {rt:<8} {r['ms']:9.1f} ms  (preprocess {r['preprocess_ms']:7.1f}, network "
                     f"{r['network_ms']:8.1f}){ratio}  setup {r['setup_s']:.1f} s, first call "
                     f"{r['first_call_s']:.1f} s, argmax agreement {r['argmax_agreement_percent']:.3f}%")
    return "\n".join(lines)


# -- the paper's Table III split: 2D / 2D-to-3D / 3D / total per preset, eager and ONNX Runtime ---------------
# V100, PyTorch (docs/design.md#the-network); only tiny's split is published
PAPER_SPLIT_MS: dict[str, dict[str, float]] = {
    "tiny": {"2d": 26.32, "2d_to_3d": 3.59, "3d": 32.89, "total": 62.80},
    "small": {"total": 90.34},
    "base": {"total": 221.28},
}
SPLIT_RUNTIMES: tuple[str, ...] = ("torch", "onnx")


@dataclass(frozen=True)
class SplitBenchConfig:
    """Per-stage inference latency of the FastOcc network for several presets in one process: 2D (image
    backbone + FPN), 2D-to-3D (depth net + LSS pooling), 3D (BEV decoder + interpolation + fusion +
    classifier), each timed alone (median of `repeats` after `warmup`). Eager PyTorch: the network's own
    stages (`run_benchmark`'s image / view / head). ONNX Runtime: each stage exported as its own fixed-rig
    graph from the export wrapper's layers (its 3D stage includes the argmax to uint8 semantics). Single
    frame (no history: the queue's cost is benchmarks/bench_temporal.py's); `input_hw` None = each
    preset's size (the paper's resolutions)."""

    presets: tuple[str, ...] = ("tiny", "small", "base")
    runtimes: tuple[str, ...] = SPLIT_RUNTIMES
    repeats: int = 5
    warmup: int = 1
    threads: int | None = None
    input_hw: tuple[int, int] | None = None
    seed: int = 0


class _Stage2D(nn.Module):
    def __init__(self, static: nn.Module) -> None:
        super().__init__()
        self.static = static

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.static.net.image_stage(images)


class _Stage2Dto3D(nn.Module):
    def __init__(self, static: nn.Module) -> None:
        super().__init__()
        self.static = static

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        from .model.network import collapse_z
        from .model.view_transform import PoolingIndex, lss_pool

        s = self.static
        depth, context = s.net.depth_net(feat)
        index = PoolingIndex(s.point_idx, s.voxel_idx)
        return collapse_z(lss_pool(depth, context, index, 1, s.cfg.coarse_grid.shape))


class _Stage3D(nn.Module):
    def __init__(self, static: nn.Module) -> None:
        super().__init__()
        self.static = static

    def forward(self, feat: torch.Tensor, bev: torch.Tensor) -> torch.Tensor:
        logits, class_dim = self.static._head(feat, bev)
        return logits.argmax(dim=class_dim).to(torch.uint8)


def _split_stages(model: FastOcc) -> tuple[list[tuple[str, nn.Module]], tuple[torch.Tensor, ...]]:
    """The three stage modules (fixed synthetic rig) and example images."""
    from .deploy import synthetic_rig
    from .deploy.static import StaticFastOcc

    static = StaticFastOcc(model, synthetic_rig(model.cfg.num_cams)).eval()
    stages = [("2d", _Stage2D(static)), ("2d_to_3d", _Stage2Dto3D(static)), ("3d", _Stage3D(static))]
    return stages, static.example_inputs()


def _stage_inputs(stages: list[tuple[str, nn.Module]], images: torch.Tensor) -> dict[str, tuple[torch.Tensor, ...]]:
    with torch.no_grad():
        feat = stages[0][1](images)
        bev = stages[1][1](feat)
    return {"2d": (images,), "2d_to_3d": (feat,), "3d": (feat, bev)}


def _time_onnx(stage: nn.Module, args: tuple[torch.Tensor, ...], cfg: SplitBenchConfig, path: str,
               threads: int) -> float:
    import logging
    import warnings

    import onnxruntime as ort

    names = [f"in{k}" for k in range(len(args))]
    log = logging.getLogger("torch.onnx")
    level = log.level
    try:
        log.setLevel(logging.ERROR)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(stage, args, path, dynamo=True, external_data=False, opset_version=18,
                              input_names=names, verbose=False)
    finally:
        log.setLevel(level)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    session = ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])
    feeds = {n: a.numpy() for n, a in zip(names, args, strict=True)}
    return _median_seconds(lambda: session.run(None, feeds), BenchConfig(repeats=cfg.repeats, warmup=cfg.warmup),
                           torch.device("cpu"))


def run_split_benchmark(cfg: SplitBenchConfig) -> dict[str, Any]:
    """Median ms of each stage and their sum per preset and runtime, ratios between presets (to the first),
    and the paper's figures beside them; a JSON-ready dict."""
    import tempfile
    from pathlib import Path

    unknown = sorted(set(cfg.runtimes) - set(SPLIT_RUNTIMES))
    if unknown:
        raise ValueError(f"unknown runtime(s) {unknown}; choose from {list(SPLIT_RUNTIMES)}")
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    threads = torch.get_num_threads()
    result: dict[str, Any] = {"presets": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name in cfg.presets:
            extra: dict[str, Any] = {"input_hw": tuple(cfg.input_hw)} if cfg.input_hw else {}
            model_cfg = preset(name, num_history=0, **extra)
            entry: dict[str, Any] = {"input_hw": list(model_cfg.input_hw), "backbone_depth": model_cfg.backbone.depth}
            if "torch" in cfg.runtimes:  # the network's own stages (eager: numba sampling kernels on the CPU)
                res = run_benchmark(BenchConfig(preset=name, repeats=cfg.repeats, warmup=cfg.warmup,
                                                input_hw=cfg.input_hw, num_history=0, seed=cfg.seed))
                ms = {"2d": res["stages"]["image"]["ms"], "2d_to_3d": res["stages"]["view"]["ms"],
                      "3d": res["heads"]["fastocc"]["ms"]}
                entry["torch"] = {**ms, "total": sum(ms.values())}
            if "onnx" in cfg.runtimes:
                stages, (images,) = _split_stages(_build(model_cfg, torch.device("cpu"), cfg.seed).eval())
                args = _stage_inputs(stages, images)
                ms = {key: 1e3 * _time_onnx(stage, args[key], cfg, str(Path(tmp) / f"{name}-{key}.onnx"), threads)
                      for key, stage in stages}
                entry["onnx"] = {**ms, "total": sum(ms.values())}
            result["presets"][name] = entry
    first = cfg.presets[0]
    for name, entry in result["presets"].items():
        for rt in cfg.runtimes:
            entry[f"{rt}_ratio_to_{first}"] = {k: v / result["presets"][first][rt][k] for k, v in entry[rt].items()}
        paper = PAPER_SPLIT_MS.get(name)
        if paper is not None:
            entry["paper_ms"] = paper
            if first in PAPER_SPLIT_MS:
                entry[f"paper_ratio_to_{first}"] = {k: v / PAPER_SPLIT_MS[first][k] for k, v in paper.items()
                                                    if k in PAPER_SPLIT_MS[first]}
    result["config"] = {"presets": list(cfg.presets), "runtimes": list(cfg.runtimes), "repeats": cfg.repeats,
                        "warmup": cfg.warmup, "threads": threads, "input_hw": list(cfg.input_hw) if cfg.input_hw
                        else None, "history": 0, "torch": torch.__version__, "device_name": "cpu",
                        "paper": "V100, PyTorch; only tiny's split is published"}
    return result


def format_split_report(result: dict[str, Any]) -> str:
    c = result["config"]
    first = c["presets"][0]
    lines = [f"latency split (ms) 2D / 2D-to-3D / 3D / total, cpu ({c['threads']} threads), median of "
             f"{c['repeats']}, single frame; ratios to {first}"]
    for name, e in result["presets"].items():
        for rt in c["runtimes"]:
            ms, ratio = e[rt], e[f"{rt}_ratio_to_{first}"]
            lines.append(f"  {name:<6} {e['input_hw'][0]}x{e['input_hw'][1]:<5} {rt:<5} " + " / ".join(
                f"{ms[k]:8.1f}" for k in ("2d", "2d_to_3d", "3d", "total")) + "   ratio " + " / ".join(
                f"{ratio[k]:.2f}" for k in ("2d", "2d_to_3d", "3d", "total")))
        if "paper_ms" in e:
            p = e["paper_ms"]
            pr = e.get(f"paper_ratio_to_{first}", {})
            lines.append(f"  {name:<6} paper (V100)    " + " / ".join(
                f"{p[k]:8.2f}" if k in p else "       -" for k in ("2d", "2d_to_3d", "3d", "total"))
                + ("   ratio " + " / ".join(f"{pr[k]:.2f}" if k in pr else "-" for k in ("2d", "2d_to_3d", "3d",
                                                                                         "total")) if pr else ""))
    return "\n".join(lines)
