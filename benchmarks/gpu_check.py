"""The GPU path in one run of a few minutes: what a lent CUDA machine should tell us first.

    bash scripts/gpu_check.sh --json gpu_check.json          # CUDA: tiny and base, nccl, 50 AMP steps
    bash scripts/gpu_check.sh --dry-run --json dry.json      # any CPU machine: the same sections, tiny shapes

Sections (each reports `status` ok / skipped / error, its seconds and its figures; one failing section does
not stop the others, and the run stops starting sections when its time budget is spent):
- `env`: torch, CUDA device, bf16 support, NCCL version, ONNX Runtime providers.
- `store`: `--store`, or a synthetic nuScenes-format world (`occdata synth`) built into a store.
- `train_amp`: `fastocc train` itself (`fastocc.train.train`) for `train_steps` optimizer steps with bf16
  autocast on CUDA (`amp = true`); step rate and data wait from its metrics.jsonl, peak GPU memory.
- `loader`: the training loader (`make_loader`, train augmentation) alone, samples/s per worker count,
  against the step rate of `train_amp` (loader/step > 1: the loader keeps up).
- `dist`: a one-process torch.distributed group (nccl on CUDA, gloo on the dry path), the trainer's DDP
  wrapping, one forward/backward/AdamW step and an all-reduce.
- `onnx`: the exported graph (`export_model`, parity-checked on the CPU) in ONNX Runtime with the CUDA and
  TensorRT execution providers where installed (CPU on the dry path); median ms and the provider that ran.
- `latency`: the fixed-rig network (`StaticFastOcc`, what `fastocc export` traces) per preset, eager and
  `torch.compile`d, fp32 and fp16 / bf16 autocast; median ms per frame (batch 1). Compiles come last and
  start only while `budget_s - compile_reserve_s` has not passed (each takes a minute or more on CUDA).

The dry path (`--dry-run`: CPU, nano at 96 x 256, gloo, CPU provider, a few steps, compile with the
"eager" backend so no C++ toolchain is needed) checks that every section runs; its figures mean nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import socket
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["DRY_PLAN", "GPU_PLAN", "SECTIONS", "CheckPlan", "run_check"]


@dataclass(frozen=True)
class CheckPlan:
    """What one check runs. `input_hw` None: each preset's own input size (the paper's)."""

    device: str
    presets: tuple[str, ...]
    input_hw: tuple[int, int] | None
    dtypes: tuple[str, ...]  # eager latency: fp32 | fp16 | bf16 (autocast)
    compile_dtypes: tuple[str, ...]
    compile_backend: str  # inductor on CUDA; "eager" on the dry path (graph capture only, no codegen)
    providers: tuple[str, ...]  # ONNX Runtime execution providers to try, each with its fallbacks
    onnx_preset: str
    train_preset: str
    train_steps: int
    batch: int
    train_workers: int
    loader_workers: tuple[int, ...]
    loader_batches: int
    dist_backend: str
    repeats: int
    warmup: int
    synth: dict[str, Any]  # occdata synth options for the store when --store is not given
    budget_s: float  # no section starts after this many seconds
    compile_reserve_s: float  # no compile starts later than this before the budget's end (one compile's time)

    def __post_init__(self) -> None:
        bad = [d for d in self.dtypes + self.compile_dtypes if d not in _DTYPES]
        if bad or self.train_steps < 1 or self.batch < 1 or self.repeats < 1 or self.budget_s <= 0:
            raise ValueError(f"bad check plan: dtypes {bad or 'ok'}, steps {self.train_steps}, batch {self.batch}, "
                             f"repeats {self.repeats}, budget {self.budget_s}")


_DTYPES = ("fp32", "fp16", "bf16")

GPU_PLAN = CheckPlan(
    device="cuda", presets=("tiny", "base"), input_hw=None, dtypes=("fp32", "fp16", "bf16"),
    compile_dtypes=("fp32", "bf16"), compile_backend="inductor",
    providers=("CUDAExecutionProvider", "TensorrtExecutionProvider"), onnx_preset="tiny", train_preset="tiny",
    train_steps=50, batch=2, train_workers=6, loader_workers=(2, 6), loader_batches=30, dist_backend="nccl",
    repeats=10, warmup=3, synth={"scenes": 6, "samples": 12, "width": 800, "height": 450}, budget_s=380.0,
    compile_reserve_s=100.0)

DRY_PLAN = CheckPlan(
    device="cpu", presets=("nano",), input_hw=(96, 256), dtypes=("fp32", "bf16"), compile_dtypes=("fp32",),
    compile_backend="eager", providers=("CPUExecutionProvider",), onnx_preset="nano", train_preset="nano",
    train_steps=2, batch=1, train_workers=1, loader_workers=(1,), loader_batches=3, dist_backend="gloo",
    repeats=1, warmup=0, synth={"scenes": 1, "samples": 2, "width": 160, "height": 90}, budget_s=600.0,
    compile_reserve_s=0.0)


@dataclass
class _Context:
    """What the sections share: the plan, a scratch folder, the store, the train step rate."""

    plan: CheckPlan
    tmp: Path
    store: Path | None = None
    train_samples_per_s: float | None = None
    t0: float = dataclasses.field(default_factory=lambda: time.perf_counter())


# -- sections ------------------------------------------------------------------------------------------------
def check_env(ctx: _Context) -> dict[str, Any]:
    import torch

    out: dict[str, Any] = {"torch": torch.__version__, "cuda_available": torch.cuda.is_available(),
                           "cpu_count": os.cpu_count(), "threads": torch.get_num_threads()}
    if torch.cuda.is_available():
        out |= {"device_name": torch.cuda.get_device_name(0), "capability": list(torch.cuda.get_device_capability(0)),
                "bf16_supported": torch.cuda.is_bf16_supported(), "cuda": torch.version.cuda,
                "nccl": _nccl_version(),
                "memory_gib": torch.cuda.get_device_properties(0).total_memory / 2**30}
    elif ctx.plan.device == "cuda":
        raise RuntimeError("no CUDA device (torch.cuda.is_available() is False); use --dry-run on a CPU machine")
    try:
        import onnxruntime as ort

        out |= {"onnxruntime": ort.__version__, "ort_providers": ort.get_available_providers()}
    except ImportError:
        out["onnxruntime"] = None
    return out


def _nccl_version() -> str:
    import torch

    v = torch.cuda.nccl.version()  # a tuple in recent torch, an int in older
    return ".".join(map(str, v)) if isinstance(v, tuple) else str(v)


def check_store(ctx: _Context) -> dict[str, Any]:
    from occdata.runtime.cluster import ClusterConfig
    from occdata.store.build import BuildConfig, build_store
    from occdata.store.reader import open_store
    from occdata.synth import SynthConfig, synthesize

    t0 = time.perf_counter()
    if ctx.store is None:
        world = synthesize(SynthConfig(out=ctx.tmp / "world", progress=False, seed=0, **ctx.plan.synth))
        t_synth = time.perf_counter() - t0
        ctx.store = ctx.tmp / "data.zarr"
        workers = 1 if ctx.plan.device == "cpu" else min(8, os.cpu_count() or 1)
        build_store(BuildConfig(root=world, out=ctx.store, gts=world / "gts", progress=False,
                                cluster=ClusterConfig(workers=workers)))
        made = {"synth_s": t_synth, "build_s": time.perf_counter() - t0 - t_synth, "synth": ctx.plan.synth}
    else:
        made = {}
    reader = open_store(ctx.store)
    return {"store": str(ctx.store), "train_samples": len(reader.split_indices("train", labelled=True)), **made}


def check_train_amp(ctx: _Context) -> dict[str, Any]:
    import torch

    from fastocc.train import TrainConfig, train

    p = ctx.plan
    n_train = check_store_samples(ctx)
    wanted = p.train_steps * p.batch
    epochs = max(1, math.ceil(wanted / n_train))
    cfg = TrainConfig(store=str(ctx.store), preset=p.train_preset, input_hw=p.input_hw, epochs=epochs,
                      batch_size=p.batch, workers=p.train_workers, device=p.device, amp=True, val_every=0,
                      keep_epochs=0, log_every=10, out=str(ctx.tmp / "run"),
                      limit_train_samples=wanted if epochs == 1 else 0)
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    result = train(cfg, progress=False)
    wall = time.perf_counter() - t0
    records = [json.loads(line) for line in (Path(cfg.out) / "metrics.jsonl").read_text().splitlines()]
    epochs_rec = [r for r in records if r.get("kind") == "epoch"]
    seconds = sum(r["seconds"] for r in epochs_rec)
    samples = epochs_rec[-1]["samples_seen"] if epochs_rec else 0
    ctx.train_samples_per_s = samples / seconds if seconds else None
    out = {"preset": p.train_preset, "amp": cfg.amp and p.device == "cuda", "batch": p.batch,
           "workers": p.train_workers, "opt_steps": result.opt_steps, "epochs": epochs, "wall_s": wall,
           "epoch_seconds": seconds, "samples_per_s": ctx.train_samples_per_s,
           "steps_per_s": result.opt_steps / seconds if seconds else None,
           "data_wait": sum(r["data_wait"] * r["seconds"] for r in epochs_rec) / seconds if seconds else None,
           "last_loss": epochs_rec[-1]["loss"] if epochs_rec else None}
    if not (out["last_loss"] is not None and math.isfinite(out["last_loss"])):
        raise RuntimeError(f"training loss is not finite: {out['last_loss']}")
    if torch.cuda.is_available():
        out["peak_gpu_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def check_store_samples(ctx: _Context) -> int:
    if ctx.store is None:
        raise RuntimeError("no store (the store section did not finish)")
    from occdata.store.reader import open_store

    n = len(open_store(ctx.store).split_indices("train", labelled=True))
    if n == 0:
        raise RuntimeError(f"{ctx.store} has no labelled train samples")
    return n


def check_loader(ctx: _Context) -> dict[str, Any]:
    from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader
    from fastocc.model import preset

    p = ctx.plan
    check_store_samples(ctx)
    H, W = p.input_hw or preset(p.train_preset).input_hw
    sample = SampleConfig(image=ImageAugConfig(height=H, width=W, train=True), bev=BevAugConfig(train=True))
    cfg = LoaderConfig(store=str(ctx.store), batch_size=p.batch, sample=sample, splits=("train",), seed=0)
    rates: dict[str, Any] = {}
    for workers in p.loader_workers:
        t0 = time.perf_counter()
        n, t_first = 0, None
        while n < p.loader_batches:  # epochs repeat when the split is small
            for _ in make_loader(cfg, num_workers=workers, pin_memory=p.device == "cuda"):
                if t_first is None:
                    t_first = time.perf_counter()
                n += 1
                if n >= p.loader_batches:
                    break
        t_end = time.perf_counter()
        sps = (n - 1) * p.batch / (t_end - t_first) if n > 1 else None
        rates[str(workers)] = {"first_batch_s": t_first - t0, "samples_per_s": sps}
    out: dict[str, Any] = {"batch": p.batch, "hw": [H, W], "workers": rates}
    step = ctx.train_samples_per_s
    if step:
        out["train_samples_per_s"] = step
        out["loader_over_step"] = {w: r["samples_per_s"] / step for w, r in rates.items() if r["samples_per_s"]}
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def check_dist(ctx: _Context) -> dict[str, Any]:
    import datetime

    import torch
    import torch.distributed as dist
    from torch import nn

    from fastocc.model import FastOcc, preset, synthetic_inputs

    p = ctx.plan
    device = torch.device("cuda", 0) if p.device == "cuda" else torch.device("cpu")
    t0 = time.perf_counter()
    dist.init_process_group(p.dist_backend, init_method=f"tcp://127.0.0.1:{_free_port()}", rank=0, world_size=1,
                            timeout=datetime.timedelta(seconds=120))
    try:
        t_init = time.perf_counter() - t0
        extra = {"input_hw": p.input_hw} if p.input_hw else {}
        cfg = preset(p.train_preset, **extra)
        torch.manual_seed(0)
        model = FastOcc(cfg).to(device).train()
        ddp = nn.parallel.DistributedDataParallel(  # as the trainer wraps it (fastocc/train/loop.py)
            model, device_ids=[0] if device.type == "cuda" else None, find_unused_parameters=True)
        opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
        inputs = synthetic_inputs(1, cfg.input_hw, cfg.num_cams, 0, str(device))
        t1 = time.perf_counter()
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
            out = ddp(inputs)
        loss = out.voxel_logits.float().mean()
        loss.backward()
        opt.step()
        total = torch.ones(1, device=device)
        dist.all_reduce(total)
        if device.type == "cuda":
            torch.cuda.synchronize()
        t_step = time.perf_counter() - t1
        if total.item() != 1.0 or not math.isfinite(loss.item()):
            raise RuntimeError(f"all-reduce over one process gave {total.item()}, loss {loss.item()}")
        return {"backend": dist.get_backend(), "world_size": dist.get_world_size(), "init_s": t_init,
                "ddp_step_s": t_step, "preset": p.train_preset}
    finally:
        dist.destroy_process_group()


@contextlib.contextmanager
def _autocast(device_type: str, dtype: str) -> Iterator[None]:
    import torch

    if dtype == "fp32":
        yield
        return
    with torch.autocast(device_type, dtype=torch.float16 if dtype == "fp16" else torch.bfloat16):
        yield


def _median_ms(fn: Callable[[], Any], warmup: int, repeats: int, device: Any) -> float:
    from fastocc.bench import BenchConfig, _median_seconds

    return 1e3 * _median_seconds(fn, BenchConfig(warmup=warmup, repeats=repeats), device)


def _static(preset_name: str, plan: CheckPlan, device: Any) -> tuple[Any, tuple[Any, ...]]:
    """The fixed-rig network (synthetic nuScenes-like rig, random weights) in eval mode and its inputs."""
    import torch

    from fastocc.deploy import synthetic_rig
    from fastocc.deploy.static import StaticFastOcc
    from fastocc.model import FastOcc, preset

    extra = {"input_hw": plan.input_hw} if plan.input_hw else {}
    cfg = preset(preset_name, **extra)
    torch.manual_seed(0)
    static = StaticFastOcc(FastOcc(cfg).eval(), synthetic_rig(cfg.num_cams)).eval()
    inputs = tuple(t.to(device) for t in static.example_inputs())
    return static.to(device), inputs


def _measure(rows: dict[str, Any], key: str, fn: Callable[[], float]) -> None:
    """rows[key] = fn(), or the one-line error: one failing dtype or compile leaves the other figures."""
    try:
        rows[key] = fn()
    except Exception as exc:  # noqa: BLE001 - a finding, reported in its cell
        rows[key] = f"error: {_one_line(exc)}"


def _compiled_ms(static: Any, inputs: tuple[Any, ...], dtype: str, rows: dict[str, Any], p: CheckPlan,
                 device: Any) -> float:
    """Compile (first call, timed into rows) and the median ms of the compiled module under `dtype`."""
    import torch

    torch._dynamo.reset()
    compiled = torch.compile(static, backend=p.compile_backend, dynamic=False)
    with _autocast(device.type, dtype):
        t0 = time.perf_counter()
        compiled(*inputs)
        if device.type == "cuda":
            torch.cuda.synchronize()
        rows[f"compile_{dtype}_s"] = time.perf_counter() - t0
        return _median_ms(lambda: compiled(*inputs), p.warmup, p.repeats, device)


def _eager_ms(static: Any, inputs: tuple[Any, ...], dtype: str, p: CheckPlan, device: Any) -> float:
    with _autocast(device.type, dtype):
        return _median_ms(lambda: static(*inputs), p.warmup, p.repeats, device)


def _latency_rows(name: str, ctx: _Context, device: Any) -> dict[str, Any]:
    """One preset: eager ms per dtype, then compile seconds and compiled ms per dtype (budget allowing)."""
    import torch

    p = ctx.plan
    static, inputs = _static(name, p, device)
    rows: dict[str, Any] = {"input_hw": list(static.cfg.input_hw), "num_history": static.cfg.num_history}
    with torch.no_grad():
        for dtype in p.dtypes:
            _measure(rows, f"eager_{dtype}_ms", lambda d=dtype: _eager_ms(static, inputs, d, p, device))
        for dtype in p.compile_dtypes:
            if time.perf_counter() - ctx.t0 > p.budget_s - p.compile_reserve_s:
                rows[f"compiled_{dtype}_ms"] = "skipped: time budget spent"
                continue
            _measure(rows, f"compiled_{dtype}_ms",
                     lambda d=dtype: _compiled_ms(static, inputs, d, rows, p, device))
    if device.type == "cuda":
        rows["peak_gpu_mib"] = torch.cuda.max_memory_allocated() / 2**20
        torch.cuda.reset_peak_memory_stats()
    return rows


def check_latency(ctx: _Context) -> dict[str, Any]:
    import torch

    p = ctx.plan
    device = torch.device(p.device)
    return {"batch": 1, "repeats": p.repeats, "compile_backend": p.compile_backend,
            "presets": {name: _latency_rows(name, ctx, device) for name in p.presets}}


_FALLBACKS = {"TensorrtExecutionProvider": ["CUDAExecutionProvider", "CPUExecutionProvider"],
              "CUDAExecutionProvider": ["CPUExecutionProvider"], "CPUExecutionProvider": []}


def check_onnx(ctx: _Context) -> dict[str, Any]:
    import numpy as np
    import onnxruntime as ort
    import torch

    from fastocc.deploy import ExportConfig, export_model, synthetic_rig

    p = ctx.plan
    static, inputs = _static(p.onnx_preset, p, torch.device("cpu"))
    path = ctx.tmp / f"{p.onnx_preset}.onnx"
    t0 = time.perf_counter()
    export_model(static.net, synthetic_rig(static.cfg.num_cams), ExportConfig(checkpoint=Path("(in memory)"),
                                                                               out=path, frames=1))
    out: dict[str, Any] = {"preset": p.onnx_preset, "export_s": time.perf_counter() - t0, "providers": {}}
    feeds = {n: t.numpy() for n, t in zip(static.input_names(), inputs, strict=True)}
    available = ort.get_available_providers()
    for provider in p.providers:
        if provider not in available:
            out["providers"][provider] = "skipped: not installed in this onnxruntime build"
            continue
        if time.perf_counter() - ctx.t0 > p.budget_s:
            out["providers"][provider] = "skipped: time budget spent"
            continue
        t1 = time.perf_counter()
        session = ort.InferenceSession(str(path), providers=[provider, *_FALLBACKS.get(provider, [])])
        session.run(None, feeds)  # TensorRT builds its engine here
        first = time.perf_counter() - t1
        times = []
        for _ in range(p.repeats):
            t2 = time.perf_counter()
            session.run(None, feeds)
            times.append(time.perf_counter() - t2)
        out["providers"][provider] = {"ms": 1e3 * statistics.median(times), "setup_and_first_run_s": first,
                                      "active": session.get_providers()[0]}
    out["input_shapes"] = {n: list(np.shape(v)) for n, v in feeds.items()}
    return out


SECTIONS: dict[str, Callable[[_Context], dict[str, Any]]] = {
    "env": check_env, "store": check_store, "train_amp": check_train_amp, "loader": check_loader,
    "dist": check_dist, "onnx": check_onnx, "latency": check_latency,
}


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:300] if text else '(no message)'}"


def run_check(plan: CheckPlan, store: Path | None = None, say: Callable[[str], None] = print,
              json_path: str | None = None) -> dict[str, Any]:
    """Every section in order; a JSON-ready dict {section: {status, seconds, ...}} plus the plan. With
    `json_path`, the result so far is rewritten after each section (a killed run keeps what it measured)."""
    from benchmarks.common import write_json
    from benchmarks.provenance import machine

    result: dict[str, Any] = {"machine": machine(), "plan": dataclasses.asdict(plan), "sections": {}}
    with tempfile.TemporaryDirectory(prefix="gpu_check-") as tmp:
        ctx = _Context(plan=plan, tmp=Path(tmp), store=store)
        for name, fn in SECTIONS.items():
            t0 = time.perf_counter()
            if t0 - ctx.t0 > plan.budget_s:
                entry: dict[str, Any] = {"status": "skipped", "reason": f"time budget {plan.budget_s:.0f} s spent"}
            else:
                try:
                    entry = {"status": "ok", **fn(ctx)}
                except Exception as exc:  # noqa: BLE001 - one section's failure is a finding, not the end
                    entry = {"status": "error", "error": _one_line(exc)}
            entry["seconds"] = time.perf_counter() - t0
            result["sections"][name] = entry
            result["total_s"] = time.perf_counter() - ctx.t0
            say(format_section(name, entry))
            if json_path:
                write_json(result, json_path)
    return result


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return str(v)


def format_section(name: str, entry: dict[str, Any]) -> str:
    """`[name] status (N s): key value, ...` with nested dicts inline."""
    body = ", ".join(f"{k} {_fmt(v)}" for k, v in entry.items() if k not in ("status", "seconds"))
    return f"[{name}] {entry['status']} ({entry['seconds']:.1f} s): {body}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dry-run", action="store_true", help="CPU, tiny shapes, gloo, CPU provider (checks the path)")
    ap.add_argument("--store", type=Path, help="a built store with a labelled train split (default: a synthetic one)")
    ap.add_argument("--budget", type=float, help="seconds after which no section starts (default: the plan's)")
    ap.add_argument("--json", help="also write the result here")
    args = ap.parse_args()
    plan = DRY_PLAN if args.dry_run else GPU_PLAN
    if args.budget:
        plan = dataclasses.replace(plan, budget_s=args.budget)
    result = run_check(plan, args.store, json_path=args.json)
    print(f"gpu_check: {'dry run' if args.dry_run else 'CUDA'} done in {result['total_s']:.0f} s; "
          + ", ".join(f"{k} {v['status']}" for k, v in result["sections"].items()))


if __name__ == "__main__":
    main()
