"""Deployment benchmark behind docs/benchmarks-deploy.md and docs/deploy.md.

For each preset, in one process: end-to-end latency per frame through `fastocc.Predictor` (6 raw uint8
1600x900 images -> preprocessing -> network -> semantics) for eager PyTorch, torch.compile and ONNX
Runtime (`run_runtime_benchmark`), and the time `fastocc export` needs (export + parity check).

    python -m benchmarks.bench_deploy --presets nano tiny --json summary.json
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import write_json
from benchmarks.provenance import machine
from fastocc.bench import RUNTIMES, RuntimeBenchConfig, format_runtime_report, run_runtime_benchmark
from fastocc.checkpoint import save_checkpoint
from fastocc.deploy import ExportConfig, export_onnx
from fastocc.model import FastOcc, preset

__all__ = ["export_seconds"]


def export_seconds(name: str) -> dict:
    """Wall time of `fastocc export` (load checkpoint, export, parity over 2 frames, write) for a random model."""
    torch.manual_seed(0)
    cfg = preset(name)
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = save_checkpoint(Path(tmp) / "c.pt", cfg, FastOcc(cfg).state_dict())
        t0 = time.perf_counter()
        rep = export_onnx(ExportConfig(checkpoint=ckpt, out=Path(tmp) / "m.onnx"))
        return {"seconds": time.perf_counter() - t0, "size_mib": rep.size_mib,
                "max_abs_diff": rep.parity.max_abs_diff, "min_agreement": rep.parity.min_agreement}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=["nano", "tiny"])
    parser.add_argument("--runtimes", nargs="+", default=list(RUNTIMES), choices=list(RUNTIMES))
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--no-export-timing", action="store_true")
    parser.add_argument("--json", type=Path, default=None, help="write the summary (and raw results) here")
    args = parser.parse_args()
    summary: dict = {"machine": machine(), "cpu_threads": torch.get_num_threads(), "presets": {}}
    for name in args.presets:
        res = run_runtime_benchmark(RuntimeBenchConfig(preset=name, runtimes=tuple(args.runtimes), device=args.device,
                                                       repeats=args.repeats, warmup=args.warmup))
        print(format_runtime_report(res), flush=True)
        entry = {"latency": res}
        if not args.no_export_timing:
            entry["export"] = export_seconds(name)
            print(f"  export {name}: {entry['export']['seconds']:.1f} s", flush=True)
        summary["presets"][name] = entry
    if args.json:
        write_json(summary, args.json)


if __name__ == "__main__":
    main()
