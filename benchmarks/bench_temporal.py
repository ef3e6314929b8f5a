"""Temporal fusion at single-frame cost: the cost of history, "concat", "cached", "recurrent".

Four models of one preset in one process, same seed: 0 previous frames (`hist0`), 16 frames with
the default fusion (`concat16`: the queue holds full V_B maps, a 1x1 conv over 17 x C2*8 channels), 16
frames with the cached fusion (`cached16`: each frame reduced once to C_r channels when current, the
queue holds the reduced maps; warp + small fusion per frame) and the recurrent state (`recurrent`: one
32-channel state warped and updated by a 1x1 ConvGRU cell per frame; training unrolls 4 frames).
Measured:

- inference, end to end per frame through `fastocc.Predictor` (6 raw uint8 1600 x 900 images ->
  preprocessing -> network -> semantics) on a moving stream, eager PyTorch and ONNX Runtime (exported
  here with its parity check), `--threads` threads (default 1; ORT intra-op threads the same);
- a training step on synthetic inputs (forward + all losses + backward, train mode, the queue carried
  between steps as in scene-sequential training), eager PyTorch.

Rounds interleave the models (round k times every model and runtime once, `--repeats` frames or steps
each, median); the reported figures are medians over rounds, ratios taken per round (a drift of the
machine's load hits every model of a round alike). Each figure comes as wall time and as the CPU time of
the calling thread (`time.thread_time`: at 1 thread torch, the numba kernels and ONNX Runtime's single
intra-op thread all compute there), which a loaded machine inflates far less than wall time; on an idle
machine the two agree. Run it alone on an idle machine for figures to quote.

    python -m benchmarks.bench_temporal --preset nano --input-hw 96 256 --rounds 3 --json out.json
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.common import write_json
from benchmarks.provenance import finish, machine
from fastocc.deploy import ExportConfig, Predictor, export_model, synthetic_rig
from fastocc.deploy.export import _stream_poses
from fastocc.losses import LossConfig, occupancy_loss
from fastocc.model import FastOcc, ModelConfig, preset, synthetic_inputs

__all__ = ["ROWS", "format_report", "run"]

ROWS: dict[str, dict[str, Any]] = {
    "hist0": {"num_history": 0},
    "concat16": {"num_history": 16, "temporal_fusion": "concat"},
    "cached16": {"num_history": 16, "temporal_fusion": "cached"},
    "recurrent": {"num_history": 16, "temporal_fusion": "recurrent", "temporal_channels": 32, "temporal_unroll": 4},
}


def _configs(name: str, input_hw: tuple[int, int] | None, channels: int) -> dict[str, ModelConfig]:
    extra: dict[str, Any] = {"input_hw": tuple(input_hw)} if input_hw else {}
    return {row: preset(name, **{"temporal_channels": channels, **extra, **over}) for row, over in ROWS.items()}


class _Stream:
    """A predictor fed a moving stream: two random frames alternating, poses ~1 m apart."""

    def __init__(self, pred: Predictor, frames: list[list[np.ndarray]], poses: list[np.ndarray]) -> None:
        self.pred, self.frames, self.poses, self.t = pred, frames, poses, 0

    def step(self) -> tuple[float, float, float]:
        """Wall seconds of one frame, the Predictor's network part of them, and this thread's CPU seconds."""
        t0, c0 = time.perf_counter(), time.thread_time()
        n = len(self.poses)
        self.pred(self.frames[self.t % 2], self.poses[self.t % n], seq_start=self.t % n == 0)
        self.t += 1
        return time.perf_counter() - t0, self.pred.times.network, time.thread_time() - c0


def _predictors(cfgs: dict[str, ModelConfig], runtimes: tuple[str, ...], threads: int, tmp: Path,
                seed: int) -> dict[tuple[str, str], _Stream]:
    rig = synthetic_rig()
    rng = np.random.default_rng(seed)
    frames = [[rng.integers(0, 256, (int(h), int(w), 3), dtype=np.uint8) for w, h in rig.image_size]
              for _ in range(2)]
    poses = _stream_poses(64, seed)
    out = {}
    for row, cfg in cfgs.items():
        torch.manual_seed(seed)
        model = FastOcc(cfg).eval()
        for rt in runtimes:
            if rt == "onnx":
                path = tmp / f"{row}.onnx"
                export_model(model, rig, ExportConfig(checkpoint=Path("(in memory)"), out=path, frames=2))
                pred = Predictor(path, threads=threads)
            else:
                pred = Predictor.from_model(model, rig, runtime="torch")
            out[(row, rt)] = _Stream(pred, frames, poses)
            print(f"  ready: {row} {rt}", flush=True)
    return out


def _train_steps(cfgs: dict[str, ModelConfig], seed: int) -> dict[str, Callable[[], tuple[float, float]]]:
    """One timed training step per call for each model (synthetic batch of 1, queue carried): wall and
    this thread's CPU seconds."""
    steps = {}
    for row, cfg in cfgs.items():
        torch.manual_seed(seed)
        net = FastOcc(cfg).train()
        inputs = synthetic_inputs(1, cfg.input_hw, cfg.num_cams, seed)
        from fastocc.bench import _random_targets

        targets = _random_targets(cfg, 1, torch.device("cpu"))
        state = {"t": 0}

        def step(net: FastOcc = net, inputs: Any = inputs, targets: Any = targets,
                 state: dict = state) -> tuple[float, float]:
            inp = type(inputs)(**{**inputs.__dict__, "seq_start": torch.tensor([state["t"] == 0])})
            state["t"] += 1
            t0, c0 = time.perf_counter(), time.thread_time()
            out = net(inp)
            loss, _ = occupancy_loss(out.voxel_logits, targets, LossConfig(), out.depth_probs, out.bev_logits)
            loss.backward()
            net.zero_grad(set_to_none=True)
            return time.perf_counter() - t0, time.thread_time() - c0

        steps[row] = step
    return steps


def _medians(samples: list[tuple[float, ...]]) -> tuple[float, ...]:
    """Per-field medians of a list of timing tuples."""
    return tuple(statistics.median(s[j] for s in samples) for j in range(len(samples[0])))


def _summary(rounds: list[dict[str, tuple[float, ...]]], row: str, names: tuple[str, ...]) -> dict[str, float]:
    """Medians over rounds of each field (in ms) and of its per-round ratio to hist0 (`ratio` for the wall
    time `ms`, `<name>_ratio` for the others)."""
    out = {}
    for j, name in enumerate(names):
        out[name] = 1e3 * statistics.median(r[row][j] for r in rounds)
        key = "ratio" if name == "ms" else f"{name.removesuffix('_ms')}_ratio"
        out[key] = statistics.median(r[row][j] / r["hist0"][j] for r in rounds)
    return out


def run(name: str = "nano", input_hw: tuple[int, int] | None = (96, 256), channels: int = 16, threads: int = 1,
        runtimes: tuple[str, ...] = ("torch", "onnx"), rounds: int = 3, repeats: int = 5, warmup: int = 3,
        train_repeats: int = 3, seed: int = 0) -> dict[str, Any]:
    """The measurement described in the module docstring; a JSON-ready dict."""
    torch.set_num_threads(threads)
    cfgs = _configs(name, input_hw, channels)
    record = machine(threads=threads)
    with tempfile.TemporaryDirectory() as tmp:
        streams = _predictors(cfgs, runtimes, threads, Path(tmp), seed)
        steps = _train_steps(cfgs, seed) if train_repeats else {}
        for s in streams.values():
            for _ in range(warmup):
                s.step()
        for st in steps.values():
            for _ in range(max(c.temporal_unroll for c in cfgs.values())):
                st()  # warm-up (allocator, caches) until the recurrent training window is full
        infer: dict[str, list[dict[str, tuple[float, ...]]]] = {rt: [] for rt in runtimes}
        train: list[dict[str, tuple[float, ...]]] = []
        for k in range(rounds):
            for rt in runtimes:
                infer[rt].append({row: _medians([streams[(row, rt)].step() for _ in range(repeats)]) for row in cfgs})
            if steps:
                train.append({row: _medians([st() for _ in range(train_repeats)]) for row, st in steps.items()})
            print(f"  round {k + 1}/{rounds}: " + ", ".join(
                f"{rt} {row} {1e3 * infer[rt][-1][row][0]:.0f} ms (cpu {1e3 * infer[rt][-1][row][2]:.0f})"
                for rt in runtimes for row in cfgs)
                + ("" if not train else ", train " + ", ".join(f"{r} {v[0]:.2f} s" for r, v in train[-1].items())),
                flush=True)
    result: dict[str, Any] = {"inference": {}, "train": {}}
    for rt in runtimes:
        result["inference"][rt] = {row: _summary(infer[rt], row, ("ms", "network_ms", "cpu_ms")) for row in cfgs}
        for v in result["inference"][rt].values():
            v["frames_per_s"] = 1e3 / v["ms"]
    if train:
        result["train"] = {row: _summary(train, row, ("ms", "cpu_ms")) for row in cfgs}
    first = next(iter(cfgs.values()))
    result["config"] = {
        "preset": name, "input_hw": list(first.input_hw), "temporal_channels": channels, "threads": threads,
        "runtimes": list(runtimes), "rounds": rounds, "repeats": repeats, "warmup": warmup,
        "train_repeats": train_repeats, "seed": seed, "rows": {row: ROWS[row] for row in cfgs},
        "goal": "history <= 1.10x hist0 frame latency in both runtimes, <= 1.15x hist0 training step (issue 35)",
    }
    result["machine"] = finish(record)
    return result


def format_report(res: dict[str, Any]) -> str:
    c, m = res["config"], res["machine"]
    lines = [f"preset {c['preset']} {c['input_hw'][0]}x{c['input_hw'][1]}, C_r {c['temporal_channels']}, "
             f"{c['threads']} thread(s), {c['rounds']} rounds x {c['repeats']} frames; 1-min load "
             f"{m['loadavg_1min']:.1f} -> {m['loadavg_1min_end']:.1f}; ratios to hist0 (wall / CPU)"]
    for rt, rows in res["inference"].items():
        for row, v in rows.items():
            lines.append(f"  infer {rt:<5} {row:<9} {v['ms']:7.1f} ms/frame ({v['frames_per_s']:5.2f} frames/s, "
                         f"CPU {v['cpu_ms']:6.1f} ms)  x{v['ratio']:.2f} / x{v['cpu_ratio']:.2f}; network "
                         f"{v['network_ms']:7.1f} ms x{v['network_ratio']:.2f}")
    for row, v in res["train"].items():
        lines.append(f"  train       {row:<9} {v['ms'] / 1e3:7.3f} s/step (CPU {v['cpu_ms'] / 1e3:6.3f} s)  "
                     f"x{v['ratio']:.2f} / x{v['cpu_ratio']:.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="nano", choices=["nano", "tiny", "small", "base"])
    ap.add_argument("--input-hw", type=int, nargs=2, default=[96, 256],
                    help="network input (default 96 256, the ablation rows' size); 0 0 = the preset's")
    ap.add_argument("--temporal-channels", type=int, default=16,
                    help="C_r of the cached queue (the recurrent row keeps its own C_s = 32)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--runtimes", nargs="+", default=["torch", "onnx"], choices=["torch", "onnx"])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=5, help="frames per model, runtime and round")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--train-repeats", type=int, default=3, help="training steps per model and round (0: skip)")
    ap.add_argument("--json", type=Path, default=None, help="write the result here")
    args = ap.parse_args(argv)
    hw = None if args.input_hw == [0, 0] else (args.input_hw[0], args.input_hw[1])
    res = run(args.preset, hw, args.temporal_channels, args.threads, tuple(args.runtimes), args.rounds,
              args.repeats, args.warmup, args.train_repeats)
    print(format_report(res))
    if args.json:
        write_json(res, args.json, indent=1)


if __name__ == "__main__":
    main()
