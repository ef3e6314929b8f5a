"""Model benchmark behind docs/benchmarks-model.md (per-stage latency).

Runs, in one process: (1) inference per stage for the tiny preset with all three heads (FastOcc head vs
3D FCN vs deconv on the same image features and V_B); (2) nano forward + backward per sample.

    python -m benchmarks.bench_model --json summary.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from benchmarks.common import write_json
from benchmarks.provenance import machine
from fastocc.bench import BenchConfig, format_report, run_benchmark
from fastocc.model import HeadKind

__all__: list[str] = []


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--head-preset", default="tiny", help="preset for the head comparison")
    parser.add_argument("--train-preset", default="nano", help="preset for the forward+backward timing")
    parser.add_argument("--json", type=Path, default=None, help="write the summary (and raw results) here")
    args = parser.parse_args()
    record = machine(threads=torch.get_num_threads(), device=args.device)
    heads = run_benchmark(
        BenchConfig(preset=args.head_preset, heads=tuple(HeadKind), device=args.device, repeats=args.repeats)
    )
    print(format_report(heads))
    train = run_benchmark(
        BenchConfig(
            preset=args.train_preset, heads=tuple(HeadKind), device=args.device, repeats=args.repeats, mode="train"
        )
    )
    print(format_report(train))
    summary = {
        "machine": record,
        "head_preset": args.head_preset,
        "fastocc_head_ms": heads["heads"]["fastocc"]["ms"],
        "fcn3d_head_ms": heads["heads"]["3dfcn"]["ms"],
        "deconv_head_ms": heads["heads"]["deconv"]["ms"],
        "fastocc_over_3dfcn_head_time": heads["fastocc_over_3dfcn_head_time"],
        "train_preset": args.train_preset,
        "fwd_bwd_s_per_sample": train["heads"]["fastocc"]["fwd_bwd_s_per_sample"],
        "fwd_loss_bwd_s_per_sample": train["heads"]["fastocc"]["fwd_loss_bwd_s_per_sample"],
        "raw": {"heads": heads, "train": train},
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "raw"}, indent=2))
    if args.json is not None:
        write_json(summary, args.json)


if __name__ == "__main__":
    main()
