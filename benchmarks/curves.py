"""Validation curve of a training run: every checkpoint of a run folder scored on val, cached in the folder.

Used by `benchmarks.bench_train curve` (the learning-curve PNG) and `benchmarks.ablations score`.
Scoring is the product's `fastocc.infer.score.score_checkpoint`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["run_checkpoints", "run_curve"]


def run_checkpoints(run: Path) -> dict[int, Path]:
    """The run's checkpoints (snap_*.pt, epoch_*.pt, last.pt) by optimizer step, one per step count."""
    from fastocc.checkpoint import load_checkpoint

    ckpts: dict[int, Path] = {}
    for p in sorted(run.glob("snap_*.pt")) + sorted(run.glob("epoch_*.pt")) + [run / "last.pt"]:
        if p.is_file():
            ckpts.setdefault(int(load_checkpoint(p).meta.get("opt_steps", 0)), p)
    return ckpts


def run_curve(run: Path, store: str, rayiou: bool, workers: int, every: int = 1) -> dict[str, Any]:
    """Val scores of every `every`-th checkpoint of `run` (and always the last), with its training loss.

    A run trained with noise_images = true is scored with noise images too. Scores are cached per
    (checkpoint name, step, store, rayiou) in run/bench_eval.json, so a re-run only scores new ones."""
    from fastocc.infer.score import score_checkpoint

    cfg = json.loads((run / "config.json").read_text())
    noise = bool(cfg.get("noise_images"))
    ckpts = run_checkpoints(run)
    cache_path = run / "bench_eval.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    steps = sorted(ckpts)
    keep = set(steps[every - 1::every]) | set(steps[-1:])
    points = []
    for step in steps:
        if step not in keep:
            continue
        p = ckpts[step]
        key = f"{p.name}@{step}@{store}@{rayiou}"
        if key not in cache:
            cache[key] = score_checkpoint(p, store, "val", rayiou=rayiou, noise_images=noise, workers=workers)
            cache_path.write_text(json.dumps(cache, indent=1))
        points.append(cache[key])
    records = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines() if ln.strip()]
    train = [r for r in records if r["kind"] == "train"]
    return {"run": str(run), "noise_images": noise, "config": cfg, "points": points,
            "loss": [(r["samples_seen"], r["loss"]) for r in train],
            "data_wait": [r["data_wait"] for r in train], "epochs": [r for r in records if r["kind"] == "epoch"]}
