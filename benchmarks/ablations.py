"""The paper's ablation tables on the synthetic world, one command per step.

World (6 train / 2 val scenes) and recipe (benchmarks/configs/learn_nano_18ep.toml, shortened to E epochs,
the same E for every row; seeds 0 and 1 per row):

    occdata synth --scenes 8 --samples 40 --seed 3 --width 800 --height 450 --out w8
    occdata build --root w8 --out w8v.zarr

Tables and the runs behind their rows (a run shared by two tables is trained once):

    head        surroundocc | deconv | 3dfcn | fastocc        (paper Table II)
    components  neither | bev-only | bev-unfold | interp-only | fastocc
                                                              (paper Table IV; BEV supervision off = w_bev 0)
    history     hist0 | hist0fuse | hist4 | hist16 | hist16cached | hist16cached64 | hist16cachedgrad |
                hist16rec   (all trained scene-sequentially)
    resolution  fastocc (96x256) | nano128 (128x352)          (paper Table III, input size only)
    tta         the best row of the tables above, flip TTA off | on (evaluation only)

Steps:

    python -m benchmarks.ablations status                    # done / missing runs, the commands to run them
    python -m benchmarks.ablations run fastocc --seed 0      # fastocc train into runs/ablate/fastocc-s0
    python -m benchmarks.ablations score                     # val mIoU (camera mask), RayIoU, geometry IoU
    python -m benchmarks.ablations latency                   # 3D-side latency of each head / FastOcc head
    python -m benchmarks.ablations steptime                  # training s/step per row, one run at a time
    python -m benchmarks.ablations tables                    # docs/ablations.md + img/ PNGs, from docs/results/

`run` resumes a run whose folder holds last.pt; it records wall time per call in ablate_run.json in the
run folder. `score` scores checkpoints with `fastocc.infer.score` (the project's metric code; learning
curves through `benchmarks.curves`) and caches per checkpoint, so it can be re-run as runs land.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import math
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from benchmarks.provenance import REPO, machine
from fastocc.train.config import TrainConfig, config_to_toml, load_config

__all__ = ["ROWS", "TABLES", "Row", "Table", "TableRow", "render_markdown", "row_config", "verdict"]

RECIPE = REPO / "benchmarks" / "configs" / "learn_nano_18ep.toml"
DEFAULT_EPOCHS = 6
SEEDS = (0, 1)
RUNS_DIR = Path("runs/ablate")
DOCS = REPO / "docs"
WORLD = ("occdata synth --scenes 8 --samples 40 --seed 3 --width 800 --height 450 --out w8\n"
         "occdata build --root w8 --out w8v.zarr")


@dataclass(frozen=True)
class Row:
    """One trained configuration: `overrides` are TrainConfig fields applied on top of the recipe."""

    name: str
    overrides: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class TableRow:
    """A table line: its label, the run (Row name) it reads, and the paper's mIoU / latency (ms) if any."""

    label: str
    row: str
    paper_miou: float | None = None
    paper_ms: float | None = None


@dataclass(frozen=True)
class Table:
    key: str
    title: str
    rows: tuple[TableRow, ...]
    note: str


ROWS: dict[str, Row] = {r.name: r for r in (
    Row("fastocc"),
    Row("3dfcn", (("head", "3dfcn"),)),
    Row("deconv", (("head", "deconv"),)),
    Row("neither", (("interp_features", False), ("w_bev", 0.0))),
    Row("bev-only", (("interp_features", False),)),
    Row("interp-only", (("w_bev", 0.0),)),
    Row("hist0", (("num_history", 0), ("scene_sequential", True))),
    Row("hist4", (("num_history", 4), ("scene_sequential", True))),
    Row("hist16", (("num_history", 16), ("scene_sequential", True))),
    Row("bev-unfold", (("interp_features", False), ("bev_height", "unfold"))),
    Row("hist0fuse", (("num_history", 0), ("scene_sequential", True), ("zero_history_fusion", True))),
    Row("hist16cached", (("num_history", 16), ("scene_sequential", True), ("temporal_fusion", "cached"))),
    # Controls of why the cached fusion loses: a wider reduction; the reduction trained
    # through the history (the queued frames' full maps reduced with gradient in training).
    Row("hist16cached64", (("num_history", 16), ("scene_sequential", True), ("temporal_fusion", "cached"),
                           ("temporal_channels", 64))),
    Row("hist16cachedgrad", (("num_history", 16), ("scene_sequential", True), ("temporal_fusion", "cached"),
                             ("temporal_grad_history", True))),
    # A constant-cost history: one recurrent BEV state (ConvGRU-style, C_s = 32), trained with
    # truncated back-propagation over 4 frames.
    Row("hist16rec", (("num_history", 16), ("scene_sequential", True), ("temporal_fusion", "recurrent"),
                      ("temporal_channels", 32), ("temporal_unroll", 4))),
    Row("nano128", (("input_hw", (128, 352)),)),
    Row("surroundocc", (("head", "deconv"), ("view_transform", "attention"))),
)}

TABLES: tuple[Table, ...] = (
    Table("head", "Head (paper Table II: ResNet-101, 640x1600, V100)", (
        TableRow("SurroundOcc*: attention view transform + 3D deconv head", "surroundocc", 37.18, 355.0),
        TableRow("Baseline: 3D deconv head", "deconv", 38.44, 306.0),
        TableRow("Baseline+: 3D FCN head", "3dfcn", 41.02, 342.0),
        TableRow("FastOcc: 2D BEV FCN + interpolation", "fastocc", 40.75, 221.0),
    ), "Paper latency is the whole network's; ours is the 3D side only (`latency`), as a ratio to the FastOcc head, "
       "except SurroundOcc*, whose view transform differs too: whole network / FastOcc's whole network. "
       "`surroundocc` = `view_transform = \"attention\"` (voxel queries, deformable spatial cross-attention, one "
       "layer; docs/model.md) with the deconv head; no depth net, so no depth loss."),
    Table("components", "Components (paper Table IV: tiny, ResNet-50, 320x800)", (
        TableRow("neither", "neither"),
        TableRow("BEV supervision only", "bev-only", 31.67),
        TableRow("BEV supervision only, channel-to-height", "bev-unfold", 31.67),
        TableRow("interpolated fusion only", "interp-only", 33.08),
        TableRow("both (= FastOcc row of the head table)", "fastocc", 34.21),
    ), "BEV supervision off = `w_bev = 0` (the BEV head still runs in training but gets no loss); interpolated "
       "fusion off = `interp_features = false`: the voxel feature is the BEV map alone, z-repeated (constant "
       "along z; `bev_height = \"repeat\"`) or, in `bev-unfold`, with its channels unfolded into the 16 height "
       "bins (`bev_height = \"unfold\"`, the paper's \"repeated and regressed to occupancy\" read as "
       "channel-to-height)."),
    Table("history", "History (scene-sequential training for every row)", (
        TableRow("0 previous frames", "hist0"),
        TableRow("0 previous frames + the fusion layer (control)", "hist0fuse"),
        TableRow("4 previous frames", "hist4"),
        TableRow("16 previous frames", "hist16"),
        TableRow("16 previous frames, cached fusion", "hist16cached"),
        TableRow("16 previous frames, cached fusion, C_r = 64 (control)", "hist16cached64"),
        TableRow("16 previous frames, cached fusion, reduction trained through the history (control)",
                 "hist16cachedgrad"),
        TableRow("history as one recurrent state (C_s = 32, unrolled over 4 frames in training)", "hist16rec"),
    ), "The paper's best result (40.75, base) uses 16 frames; it gives no 0/4/16 table, so no paper column. "
       "`hist0fuse` has the history rows' fusion layer (1x1 conv + BN + ReLU) over the current map alone, so it "
       "differs from `hist16` only by the history. `hist16cached` (`temporal_fusion = \"cached\"`) reduces each "
       "frame once, when current, to 16 channels and queues those; per frame only their warp and a small "
       "residual fusion run (docs/model.md). Its two controls: `hist16cached64` reduces to 64 channels; "
       "`hist16cachedgrad` (`temporal_grad_history`) keeps the queued frames' full maps in training and reduces "
       "them with gradient, so the reduction learns from the history too (the same forward values; inference "
       "keeps the cache). `hist16rec` (`temporal_fusion = \"recurrent\"`) carries one 32-channel state forward "
       "instead of a queue: per frame one warp and a gated 1x1 update, whatever the history's length; training "
       "recomputes the last 4 frames with gradient (docs/model.md)."),
    Table("resolution", "Input resolution (paper Table III: backbone and input size)", (
        TableRow("nano, 96x256 (= FastOcc row of the head table)", "fastocc"),
        TableRow("nano, 128x352", "nano128"),
    ), "The paper's Table III varies the backbone (ResNet-50 / 101) and the input (320x800, 640x1600) at full "
       "size; its rows are not comparable with nano's, so no paper column. Its latency split 2D / 2D-to-3D / 3D "
       "is `fastocc bench --stage-split --preset tiny --preset small --preset base` (docs/benchmarks.md)."),
)


# -- configs ------------------------------------------------------------------------------------------
def run_name(row: str, seed: int) -> str:
    return f"{row}-s{seed}"


def row_config(row: str, seed: int, epochs: int, store: str | None = None, runs_dir: Path = RUNS_DIR,
               threads: int | None = None) -> TrainConfig:
    """The recipe with the row's overrides, E epochs (every epoch checkpoint kept for the curves), one seed."""
    if row not in ROWS:
        raise SystemExit(f"unknown row {row!r}; rows: {', '.join(ROWS)}")
    over: dict[str, Any] = dict(ROWS[row].overrides)
    over.update(epochs=epochs, seed=seed, keep_epochs=epochs, out=str(runs_dir / run_name(row, seed)))
    if store is not None:
        over["store"] = store
    if threads is not None:
        over["threads"] = threads
    return load_config(RECIPE, over)


# -- run ------------------------------------------------------------------------------------------------
def epoch_records(run: Path) -> list[dict[str, Any]]:
    path = run / "metrics.jsonl"
    if not path.is_file():
        return []
    recs = [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]
    return [r for r in recs if r.get("kind") == "epoch"]


def epochs_done(run: Path) -> int:
    recs = epoch_records(run)
    return max((int(r["epoch"]) for r in recs), default=0) if (run / "last.pt").is_file() else 0


def epoch_rates(run: Path) -> list[float]:
    """Epoch seconds / optimizer steps in that epoch, in epoch order (metrics.jsonl epoch records)."""
    recs = sorted(epoch_records(run), key=lambda r: r["epoch"])
    rates, prev = [], 0
    for r in recs:
        steps = int(r["opt_step"]) - prev
        prev = int(r["opt_step"])
        if steps > 0:
            rates.append(float(r["seconds"]) / steps)
    return rates


def seconds_per_step(run: Path) -> float | None:
    """Median over epochs of epoch seconds / optimizer steps in that epoch."""
    rates = epoch_rates(run)
    return statistics.median(rates) if rates else None


def run_row(row: str, seed: int, epochs: int, store: str | None, threads: int | None, runs_dir: Path) -> int:
    """`fastocc train` for one row and seed; --resume when the folder holds last.pt. Returns the exit code."""
    cfg = row_config(row, seed, epochs, store, runs_dir, threads)
    out = Path(cfg.out)
    if epochs_done(out) >= epochs:
        print(f"{out}: already done ({epochs} epochs)")
        return 0
    out.parent.mkdir(parents=True, exist_ok=True)
    toml = out.parent / "configs" / f"{out.name}.toml"
    toml.parent.mkdir(exist_ok=True)
    t0 = time.time()
    _open_call(out, t0)
    rc = _train(cfg, toml, resume=(out / "last.pt").is_file())
    _record_wall(out, t0, time.time(), rc)
    return rc


def _train(cfg: TrainConfig, toml: Path, resume: bool = False) -> int:
    """Write cfg to `toml` and run `fastocc train --config toml` from this checkout; the exit code."""
    toml.write_text(config_to_toml(cfg))
    cmd = [sys.executable, "-m", "cli.fastocc_cli", "train", "--config", str(toml), "--no-progress"]
    if resume:
        cmd.append("--resume")
    print("$", shlex.join(cmd), flush=True)
    return subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(REPO)}).returncode


def _open_call(out: Path, start: float) -> None:
    """Log a call in ablate_run.json before it trains, so that a call killed with SIGKILL (no end record)
    still counts. Its wall time is closed here, at the next call, up to the last write of
    metrics.jsonl (every few steps), and marked estimated."""
    log = _wall_log(out)
    metrics = out / "metrics.jsonl"
    for c in log["calls"]:
        if c["wall_s"] is None:
            last = metrics.stat().st_mtime if metrics.is_file() else c["start"]
            c.update(wall_s=max(0.0, last - c["start"]), rc="killed", estimated=True)
    log["calls"].append({"start": start, "wall_s": None, "rc": None})
    _write_wall_log(out, log)


def _record_wall(out: Path, start: float, end: float, rc: int) -> None:
    log = _wall_log(out)
    call = next((c for c in log["calls"] if c["start"] == start), None)
    if call is None:
        call = {"start": start}
        log["calls"].append(call)
    call.update(wall_s=end - start, rc=rc, epochs_done=epochs_done(out), loadavg_1min=os.getloadavg()[0])
    _write_wall_log(out, log)


def _wall_log(out: Path) -> dict[str, Any]:
    path = out / "ablate_run.json"
    return json.loads(path.read_text()) if path.is_file() else {"calls": []}


def _write_wall_log(out: Path, log: dict[str, Any]) -> None:
    log["wall_s"] = sum(c["wall_s"] or 0.0 for c in log["calls"])
    _save(log, out / "ablate_run.json")


# -- status ---------------------------------------------------------------------------------------------
def all_runs() -> list[tuple[str, int]]:
    return [(row, seed) for row in ROWS for seed in SEEDS]


def run_state(run: Path, epochs: int) -> str:
    cfg_path = run / "config.json"
    if cfg_path.is_file() and json.loads(cfg_path.read_text()).get("epochs") != epochs:
        return "stale (other E)"
    done = epochs_done(run)
    return "done" if done >= epochs else (f"partial ({done}/{epochs} epochs)" if (run / "last.pt").is_file()
                                          else "missing")


def lane_commands(todo: Sequence[tuple[str, int]], epochs: int, store: str | None, runs_dir: Path,
                  lanes: int = 2) -> list[str]:
    """At most `lanes` background chains (nohup, one log each), each running its share of `todo` in turn (a
    failed run does not stop its lane); 1 torch thread per run when two share the 2 cores. The two seeds
    of a row land on different lanes, so they run side by side under the same load."""
    threads = 1 if lanes > 1 and len(todo) > 1 else 2
    extra = f" --epochs {epochs} --threads {threads}" + (f" --store {shlex.quote(store)}" if store else "")
    extra += f" --runs-dir {shlex.quote(str(runs_dir))}" if runs_dir != RUNS_DIR else ""
    me = _self_command()
    cmds = []
    for k in range(min(lanes, len(todo))):
        share = todo[k::lanes]
        chain = "; ".join(f"{me} run {r} --seed {s}{extra}" for r, s in share)
        log = runs_dir / "logs" / f"lane{k}.log"
        cmds.append(f"mkdir -p {runs_dir}/logs && nohup bash -c {shlex.quote(chain)} > {log} 2>&1 &")
    return cmds


def _self_command() -> str:
    """This module's command line from the current folder: `python -m` finds the package only from the
    repository root, so elsewhere the root goes on PYTHONPATH."""
    py = f"{shlex.quote(sys.executable)} -m benchmarks.ablations"
    return py if Path.cwd().resolve() == REPO else f"PYTHONPATH={shlex.quote(str(REPO))} {py}"


def status(epochs: int, store: str | None, runs_dir: Path) -> list[tuple[str, int]]:
    todo = []
    for row, seed in all_runs():
        state = run_state(runs_dir / run_name(row, seed), epochs)
        print(f"  {run_name(row, seed):<16} {state}")
        if state.startswith("stale"):
            print(f"    {runs_dir / run_name(row, seed)} was trained with another E: move it away to rerun it")
        elif state != "done":
            todo.append((row, seed))
    print(f"{len(all_runs()) - len(todo)} of {len(all_runs())} runs done (E = {epochs}).")
    if todo:
        print("Run the missing ones, two at a time in the background (re-run `status` any time; each resumes):")
        for c in lane_commands(todo, epochs, store, runs_dir):
            print("  " + c)
    return todo


# -- score ----------------------------------------------------------------------------------------------
def load_results(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {"runs": {}}


def score_run(run: Path, store: str, workers: int) -> dict[str, Any]:
    """Final scores of last.pt (mIoU camera mask, RayIoU, geometry IoU) and the val-mIoU learning curve
    over the epoch checkpoints (`benchmarks.curves`), both cached in the run folder."""
    from benchmarks.curves import run_curve
    from fastocc.infer.score import score_checkpoint

    curve = run_curve(run, store, rayiou=False, workers=workers)
    steps = int(_last_meta(run).get("opt_steps", -1))
    final = _cached(run / "ablate_score.json", steps, store,
                    lambda: score_checkpoint(run / "last.pt", store, "val", rayiou=True, workers=workers))
    wall = json.loads((run / "ablate_run.json").read_text()) if (run / "ablate_run.json").is_file() else {}
    return {"miou": final["miou"], "rayiou": final["rayiou"], "geo_iou": final["geo_iou"],
            "frames_per_s": final.get("frames_per_s"), "opt_steps": steps, "s_per_step": seconds_per_step(run),
            "wall_s": wall.get("wall_s"), "curve": [[p["samples_seen"], p["miou"]] for p in curve["points"]],
            "loss": curve["loss"]}


def _last_meta(run: Path) -> dict[str, Any]:
    from fastocc.checkpoint import load_checkpoint

    return load_checkpoint(run / "last.pt").meta


def _cached(cache: Path, steps: int, store: str, compute: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """compute(), kept in `cache` (a JSON dict) and reused while last.pt's step count and the store match."""
    if cache.is_file():
        hit = json.loads(cache.read_text())
        if hit.get("opt_steps") == steps and hit.get("store") == store:
            return hit
    out = {**compute(), "opt_steps": steps, "store": store}
    _save(out, cache)
    return out


def score_tta(run: Path, store: str, workers: int) -> dict[str, Any]:
    """Flip TTA off and on for one run's last.pt (`score_checkpoint` each); cached in the run folder
    (ablate_tta.json) per checkpoint, like the scores."""
    from fastocc.infer.score import score_checkpoint

    def both() -> dict[str, Any]:
        out: dict[str, Any] = {"on" if tta else "off": score_checkpoint(run / "last.pt", store, "val", tta=tta,
                                                                        workers=workers) for tta in (False, True)}
        out["time_factor"] = out["on"]["infer_seconds"] / out["off"]["infer_seconds"]
        out["loadavg_1min"] = os.getloadavg()[0]
        return {"tta": out}

    return _cached(run / "ablate_tta.json", int(_last_meta(run).get("opt_steps", -1)), store, both)["tta"]


def best_row(results: dict[str, Any]) -> str | None:
    """The row of the tables with the highest mean mIoU, once every one of their rows has both seeds."""
    rows = {tr.row for t in TABLES for tr in t.rows}
    means = {r: _seed_values(results, r, "miou") for r in rows}
    if any(len(v) < len(SEEDS) for v in means.values()):
        return None
    return max(means, key=lambda r: statistics.fmean(means[r]))


def score(epochs: int, store: str, workers: int, runs_dir: Path, results_path: Path, tta_row: str | None) -> None:
    """Score every finished run into results_path. Holds an fcntl lock beside it for the whole
    read-modify-write, so a background watcher and a manual call cannot overwrite each other's rows."""
    with _results_lock(results_path):
        _score(epochs, store, workers, runs_dir, results_path, tta_row)


@contextlib.contextmanager
def _results_lock(path: Path) -> Iterator[None]:
    """An fcntl lock beside the results JSON, held by every read-modify-write of it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _score(epochs: int, store: str, workers: int, runs_dir: Path, results_path: Path, tta_row: str | None) -> None:
    results = load_results(results_path)
    results.update(epochs=epochs, store=store, seeds=list(SEEDS), recipe=str(RECIPE.relative_to(REPO)))
    for row, seed in all_runs():
        run = runs_dir / run_name(row, seed)
        if run_state(run, epochs) != "done":
            continue
        print(f"scoring {run} ...", flush=True)
        results["runs"][run_name(row, seed)] = {"row": row, "seed": seed, **score_run(run, store, workers)}
        _save(results, results_path)
    row = tta_row or best_row(results)
    if row is None:
        print("TTA waits for every row of the head / components / history tables (or pass --tta-row).")
    else:
        tta = {"row": row, "runs": {}}
        for seed in SEEDS:
            run = runs_dir / run_name(row, seed)
            if run_state(run, epochs) == "done":
                print(f"TTA off/on for {run} ...", flush=True)
                tta["runs"][run_name(row, seed)] = score_tta(run, store, workers)
        if tta["runs"]:
            results["tta"] = tta
        else:  # the best row's runs live in another runs folder: keep the TTA already scored
            print(f"TTA: no finished run of {row} under {runs_dir}; the recorded TTA is kept")
    results["machine"] = machine()
    _save(results, results_path)
    print(f"wrote {results_path}")


def _save(data: dict[str, Any], path: Path) -> None:
    """Write a JSON dict atomically: a crash mid-write leaves the old file whole."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


# -- latency --------------------------------------------------------------------------------------------
def latency(preset: str, repeats: int, rounds: int, threads: int | None, results_path: Path) -> dict[str, Any]:
    """3D-side (head stage) inference latency of the three heads in one process (fastocc.bench: same V_B and
    image features for each head, warm-up then the median of `repeats`), `rounds` times; the reported ms and
    ratios are medians over rounds (the ratio per round, so slow drifts of the machine's load cancel)."""
    from fastocc.bench import BenchConfig, run_benchmark
    from fastocc.model import HeadKind

    heads = (HeadKind.FASTOCC, HeadKind.FCN3D, HeadKind.DECONV)
    load = os.getloadavg()[0]
    per_round, whole = [], []
    for _ in range(rounds):
        res = run_benchmark(BenchConfig(preset=preset, heads=heads, repeats=repeats, threads=threads))
        per_round.append({h: v["ms"] for h, v in res["heads"].items()})
        sur = run_benchmark(BenchConfig(preset=preset, heads=(HeadKind.DECONV,), repeats=repeats, threads=threads,
                                        view_transform="attention"))
        whole.append({"fastocc": res["heads"]["fastocc"]["total_ms"],
                      "surroundocc": sur["heads"]["deconv"]["total_ms"],
                      # SurroundOcc*'s split: its 2D-to-3D is the attention transform, its 3D the deconv head
                      "fastocc_2d_to_3d": res["stages"]["view"]["ms"],
                      "surroundocc_2d_to_3d": sur["stages"]["view"]["ms"],
                      "fastocc_3d": res["heads"]["fastocc"]["ms"], "surroundocc_3d": sur["heads"]["deconv"]["ms"]})
    ms = {h.value: statistics.median(r[h.value] for r in per_round) for h in heads}
    ratio = {h.value: statistics.median(r[h.value] / r["fastocc"] for r in per_round) for h in heads}
    ratio["surroundocc"] = statistics.median(r["surroundocc"] / r["fastocc"] for r in whole)  # whole network
    for part in ("2d_to_3d", "3d"):
        ratio[f"surroundocc_{part}"] = statistics.median(r[f"surroundocc_{part}"] / r[f"fastocc_{part}"] for r in whole)
    out = {"head_ms": ms, "ratio_to_fastocc": ratio, "rounds_ms": per_round, "config": res["config"],
           "whole_ms": {k: statistics.median(r[k] for r in whole) for k in whole[0]}, "whole_rounds_ms": whole,
           "loadavg_1min": load,
           "command": f"python -m benchmarks.ablations latency --preset {preset} --repeats {repeats} --rounds {rounds}"
                      + (f" --threads {threads}" if threads else "")}
    with _results_lock(results_path):
        results = load_results(results_path)
        results["latency"] = out
        _save(results, results_path)
    for h in ms:
        print(f"  head {h:<8} {ms[h]:8.1f} ms  x{out['ratio_to_fastocc'][h]:.2f} of the FastOcc head")
    return out


def _timed_s_per_step(run: Path) -> float:
    """Seconds per optimizer step of a timing run's 2nd epoch (the 1st carries the warm-up)."""
    rates = epoch_rates(run)
    if len(rates) < 2:
        raise SystemExit(f"{run}: the timing run did not finish 2 epochs (its output is above)")
    return rates[1]


def step_time(rows: Sequence[str], samples: int, rounds: int, threads: int | None, store: str | None,
              work_dir: Path, results_path: Path) -> dict[str, Any]:
    """Training seconds per step of each row, one run at a time: the row's config on the first `samples`
    training samples for 2 epochs, timed on the 2nd; rows interleave round by round so that a drift of the
    machine's load hits each; medians over rounds, ratios to rows[0] per round. Run it on an idle machine."""
    per_round: list[dict[str, float]] = []
    load = os.getloadavg()[0]
    for k in range(rounds):
        per_round.append({})
        for row in rows:
            cfg = replace(row_config(row, 0, 2, store, work_dir / f"round{k}", threads),
                          limit_train_samples=samples, keep_epochs=1)
            out = Path(cfg.out)
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir(parents=True)
            if _train(cfg, out / "timing.toml") != 0:
                raise SystemExit(f"timing run of {row} failed (its output is above)")
            per_round[-1][row] = _timed_s_per_step(out)
            print(f"  round {k + 1}/{rounds} {row:<12} {per_round[-1][row]:.3f} s/step", flush=True)
    out = {"s_per_step": {r: statistics.median(p[r] for p in per_round) for r in rows},
           "ratio": {r: statistics.median(p[r] / p[rows[0]] for p in per_round) for r in rows},
           "rounds": per_round, "samples": samples, "threads": threads, "loadavg_1min": load,
           "command": f"python -m benchmarks.ablations steptime --rows {','.join(rows)} --samples {samples} "
                      f"--rounds {rounds}" + (f" --threads {threads}" if threads else "")}
    with _results_lock(results_path):
        results = load_results(results_path)
        results["step_time"] = out
        _save(results, results_path)
    return out


def _step_time_note(st: dict[str, Any] | None) -> str:
    if not st:
        return "Training cost alone: pending (`python -m benchmarks.ablations steptime` on an idle machine)."
    first = next(iter(st["s_per_step"]))
    per = ", ".join(f"{r} {v:.2f}" + ("" if r == first else f" ({st['ratio'][r]:.2f}x)")
                    for r, v in st["s_per_step"].items())
    return (f"Training cost measured alone (one run at a time on the idle machine, {st['threads'] or 'default'} "
            f"thread(s), 2nd epoch of a {st['samples']}-sample run, median of {len(st['rounds'])} interleaved "
            f"rounds; ratio to {first}): s/step {per}; `{st['command']}`. Use these, not the s/step column, "
            "to compare training cost.")


# -- tables ---------------------------------------------------------------------------------------------
def _seed_values(results: dict[str, Any], row: str, metric: str) -> list[float]:
    vals = [results["runs"].get(run_name(row, s), {}).get(metric) for s in SEEDS]
    return [float(v) for v in vals if v is not None]


def _per_seed(results: dict[str, Any], row: str, metric: str) -> list[float | None]:
    return [results["runs"].get(run_name(row, s), {}).get(metric) for s in SEEDS]


def verdict(a: Sequence[float], b: Sequence[float]) -> str:
    """Compare two rows' per-seed values: "pending" without every seed; "not resolved" when the means differ
    by less than the larger seed spread (max - min) of the two rows; else "A > B" / "A < B" with the gap."""
    if len(a) < len(SEEDS) or len(b) < len(SEEDS):
        return "pending"
    gap = statistics.fmean(a) - statistics.fmean(b)
    spread = max(max(a) - min(a), max(b) - min(b))
    if abs(gap) < spread or gap == 0:
        return f"not resolved (|gap| {100 * abs(gap):.2f} < seed spread {100 * spread:.2f})"
    return f"{'>' if gap > 0 else '<'} by {100 * abs(gap):.2f} (seed spread {100 * spread:.2f})"


def _pct(vals: Sequence[float | None]) -> str:
    """Per-seed values in percent and their mean; a missing seed shows as "pending" (no mean then)."""
    if all(v is None for v in vals) or not vals:
        return "pending"
    if len(vals) < len(SEEDS) or any(v is None for v in vals):
        return " / ".join("pending" if v is None else f"{100 * v:.2f}" for v in vals)
    return " / ".join(f"{100 * v:.2f}" for v in vals) + f" (mean {100 * statistics.fmean(vals):.2f})"


def _num(v: float | None, fmt: str) -> str:
    return "pending" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def _table_lines(t: Table, results: dict[str, Any]) -> list[str]:
    lat = results.get("latency", {}).get("ratio_to_fastocc", {})
    head = t.key == "head"
    cols = ["row", "paper mIoU"] + (["paper ms (ratio)"] if head else []) + [
        "mIoU s0 / s1 (mean)", "RayIoU s0 / s1 (mean)", "geometry IoU (mean)", "s/step (mean)"]
    cols += ["3D-side latency / FastOcc head"] if head else []
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for tr in t.rows:
        geo, sps = _seed_values(results, tr.row, "geo_iou"), _seed_values(results, tr.row, "s_per_step")
        cells = [f"{tr.label} (`{tr.row}`)", _num(tr.paper_miou, ".2f") if tr.paper_miou else "-"]
        if head:
            cells.append(f"{tr.paper_ms:.0f} ({tr.paper_ms / 221.0:.2f})" if tr.paper_ms else "-")
        cells += [_pct(_per_seed(results, tr.row, "miou")), _pct(_per_seed(results, tr.row, "rayiou")),
                  _num(100 * statistics.fmean(geo) if len(geo) == len(SEEDS) else None, ".2f"),
                  _num(statistics.fmean(sps) if len(sps) == len(SEEDS) else None, ".3f")]
        if head:
            whole = " (whole network)" if tr.row == "surroundocc" and lat.get(tr.row) is not None else ""
            cells.append(_num(lat.get(tr.row), ".2f") + whole)
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _comparison_lines(t: Table, results: dict[str, Any]) -> list[str]:
    """Every pair of rows, for mIoU and RayIoU, with the paper's order where it gives both mIoUs."""
    out = []
    for i, a in enumerate(t.rows):
        for b in t.rows[i + 1:]:
            m = verdict(_seed_values(results, a.row, "miou"), _seed_values(results, b.row, "miou"))
            r = verdict(_seed_values(results, a.row, "rayiou"), _seed_values(results, b.row, "rayiou"))
            line = f"- `{a.row}` vs `{b.row}`: mIoU {m}; RayIoU {r}"
            if a.paper_miou is not None and b.paper_miou is not None and a.paper_miou != b.paper_miou:
                paper = ">" if a.paper_miou > b.paper_miou else "<"
                agree = ("pending" if m == "pending" else "not resolved" if m.startswith("not") else
                         "agrees" if m.startswith(paper) else "disagrees")
                line += f"; paper {paper} by {abs(a.paper_miou - b.paper_miou):.2f}: {agree}"
            out.append(line)
    return out


def _latency_note(lat: dict[str, Any] | None) -> str:
    if not lat:
        return "3D-side latency: pending (`python -m benchmarks.ablations latency`)."
    c, ms, rounds = lat["config"], lat["head_ms"], len(lat.get("rounds_ms", [1]))
    whole = lat.get("whole_ms")
    whole_text = "" if not whole else (f"; whole network: FastOcc {whole['fastocc']:.0f} ms, SurroundOcc* "
                                       f"{whole['surroundocc']:.0f} ms")
    r = lat["ratio_to_fastocc"]
    if "surroundocc_3d" in r:
        whole_text += (f" (SurroundOcc* / FastOcc: 2D-to-3D {r['surroundocc_2d_to_3d']:.2f}x, 3D "
                       f"{r['surroundocc_3d']:.2f}x, whole {r['surroundocc']:.2f}x)")
    return (f"3D-side latency ({c['preset']} {c['input_hw'][0]}x{c['input_hw'][1]}, {c['device_name']}, "
            f"{c['threads']} threads, median of {c['repeats']} x {rounds} rounds, "
            f"1-min load {lat['loadavg_1min']:.1f}): "
            + ", ".join(f"{h} {v:.0f} ms" for h, v in ms.items()) + whole_text + f"; `{lat['command']}`.")


def _tta_lines(results: dict[str, Any]) -> list[str]:
    tta = results.get("tta")
    if not tta or not tta.get("runs"):
        return ["Pending: `score` runs it for the best row of the tables above once all their runs are done.", ""]
    runs = [tta["runs"][k] for k in sorted(tta["runs"])]
    lines = [f"Best row: `{tta['row']}`.", "", "| TTA | mIoU s0 / s1 (mean) | RayIoU s0 / s1 (mean) | time factor |",
             "|---|---|---|---|"]
    for key in ("off", "on"):
        factor = "1.00" if key == "off" else f"{statistics.fmean(r['time_factor'] for r in runs):.2f}"
        lines.append(f"| {key} | {_pct([r[key]['miou'] for r in runs])} | "
                     f"{_pct([r[key]['rayiou'] for r in runs])} | {factor} |")
    off, on = [r["off"]["miou"] for r in runs], [r["on"]["miou"] for r in runs]
    lines += ["", f"- TTA on vs off: mIoU {verdict(on, off)}", ""]
    return lines


def _budget_line(results: dict[str, Any], epochs: int) -> str:
    """E, steps per run and the measured wall minutes per run of each row (mean over its seeds)."""
    walls = {}
    for row in dict.fromkeys(tr.row for t in TABLES for tr in t.rows):
        w = _seed_values(results, row, "wall_s")
        if w:
            walls[row] = statistics.fmean(w) / 60
    measured = ", ".join(f"{r} {m:.0f}" for r, m in walls.items()) or "none yet"
    return (f"Budget: E = {epochs} is {240 * epochs} optimizer steps per run (240 training samples, batch 1). "
            f"Measured wall minutes per run (mean over seeds; two runs side by side at 1 thread each, with the "
            f"scoring of finished runs beside them for part of the time): {measured}. {len(all_runs())} runs: the "
            f"{len(all_runs()) // len(SEEDS)} rows below x {len(SEEDS)} seeds.")


def render_markdown(results: dict[str, Any], epochs: int, png: dict[str, str] | None = None,
                    readings: dict[str, str] | None = None) -> str:
    """docs/ablations.md from the results JSON: "pending" where runs are missing (pure function)."""
    png, readings = png or {}, readings or {}
    lines = ["# Ablations on the synthetic world", "",
             f"World: 8 scenes x 40 samples (6 train / 2 val; store `{results.get('store', 'w8v.zarr')}`), recipe "
             f"`{RECIPE.relative_to(REPO)}` shortened to **E = {epochs} epochs** for every row, seeds "
             f"{', '.join(map(str, SEEDS))}. Metrics in percent on the val scenes: mIoU with the camera mask, "
             "RayIoU (no mask), geometry IoU (occupied vs free, "
             "camera mask); s/step = median over epochs of epoch seconds / optimizer steps (machine load and "
             "threads vary between runs: compare the `latency` ratios for cost). Where two rows differ by "
             "less than the larger seed spread (max - min over seeds) the comparison says **not resolved**.", "",
             _budget_line(results, epochs), "", _step_time_note(results.get("step_time")), ""]
    for t in TABLES:
        lines += [f"## {t.title}", "", *_table_lines(t, results), "", t.note, ""]
        if t.key == "head":
            lines += [_latency_note(results.get("latency")), ""]
        lines += [*_comparison_lines(t, results), ""]
        if t.key in png:
            lines += [f"![{t.key} learning curves]({png[t.key]})", ""]
        lines += _reading_block(t.key, readings)
    lines += ["## Flip TTA for the best model", "", *_tta_lines(results)]
    if "tta" in png:
        lines += [f"![tta learning curves]({png['tta']})", ""]
    lines += _reading_block("tta", readings)
    lines += _commands_section(epochs)
    return "\n".join(lines) + "\n"


READING_PENDING = "Reading: pending (written after the runs: where we agree with the paper, where not, and why)."
_READING = re.compile(r"<!-- reading:(\w+) -->\n(.*?)\n<!-- /reading -->", re.S)


def _reading_block(key: str, readings: dict[str, str]) -> list[str]:
    return [f"<!-- reading:{key} -->", readings.get(key, READING_PENDING), "<!-- /reading -->", ""]


def readings_of(md_text: str) -> dict[str, str]:
    """The hand-written paragraphs between the reading markers of an existing docs/ablations.md (kept by
    `tables`, which rewrites everything else)."""
    return {m.group(1): m.group(2) for m in _READING.finditer(md_text)}


def _commands_section(epochs: int) -> list[str]:
    return ["## Commands", "", "```", WORLD, f"python -m benchmarks.ablations status --epochs {epochs}   "
            "# prints the nohup commands for the missing runs (two lanes)",
            f"python -m benchmarks.ablations run ROW --seed S --epochs {epochs} [--threads 1]",
            f"python -m benchmarks.ablations score --epochs {epochs}", "python -m benchmarks.ablations latency",
            "python -m benchmarks.ablations steptime   # on an idle machine",
            f"python -m benchmarks.ablations tables --epochs {epochs}", "```", "",
            f"Rows: {', '.join(f'`{r}`' for r in ROWS)}. Raw numbers: `docs/results/ablations.json`.", ""]


def plot_curves(results: dict[str, Any], rows: Sequence[str], title: str, path: Path) -> bool:
    """Val mIoU against samples seen, one colour per row, solid seed 0 / dashed seed 1. False if no data."""
    series = [(r, s, results["runs"][run_name(r, s)]["curve"]) for r in rows for s in SEEDS
              if run_name(r, s) in results["runs"] and results["runs"][run_name(r, s)].get("curve")]
    if not series:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    colours = {r: f"C{i}" for i, r in enumerate(rows)}
    for r, s, curve in series:
        xs, ys = zip(*curve, strict=True)
        ax.plot(xs, [100 * y for y in ys], color=colours[r], ls="-" if s == SEEDS[0] else "--", marker="o", ms=3,
                label=f"{r} seed {s}")
    ax.set(xlabel="training samples seen", ylabel="val mIoU % (camera mask)", title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def tables(results_path: Path, md_path: Path, epochs: int) -> str:
    results = load_results(results_path)
    if results.get("epochs", epochs) != epochs:
        raise SystemExit(f"{results_path} holds runs of E = {results['epochs']} epochs, not {epochs} (pass --epochs)")
    png = {}
    groups = [(t.key, [tr.row for tr in t.rows], t.title) for t in TABLES]
    if results.get("tta", {}).get("row"):
        groups.append(("tta", [results["tta"]["row"]], "best row (TTA table)"))
    for key, rows, title in groups:
        path = md_path.parent / "img" / f"{md_path.stem}_{key}.png"  # pictures live in docs/img/
        if plot_curves(results, rows, title, path):
            png[key] = f"img/{path.name}"
    readings = readings_of(md_path.read_text()) if md_path.is_file() else {}
    text = render_markdown(results, epochs, png, readings)
    md_path.write_text(text)
    print(f"wrote {md_path}" + (f" and {', '.join(png.values())}" if png else " (no curves yet)"))
    return text


# -- command line ---------------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--epochs", type=int, default=DEFAULT_EPOCHS, help=f"E, the same for every row "
                        f"(default {DEFAULT_EPOCHS})")
    common.add_argument("--store", default=None, help="store (default: the recipe's, w8v.zarr)")
    common.add_argument("--runs-dir", type=Path, default=RUNS_DIR, help=f"run folders (default {RUNS_DIR})")
    common.add_argument("--results", type=Path, default=DOCS / "results" / "ablations.json", help="raw results JSON")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", parents=[common], help="train one row and seed (resumes a started run)")
    r.add_argument("row", choices=sorted(ROWS), help="; ".join(
        f"{n}: " + (", ".join(f"{k}={v}" for k, v in row.overrides) or "the recipe") for n, row in ROWS.items()))
    r.add_argument("--seed", type=int, required=True, choices=SEEDS)
    r.add_argument("--threads", type=int, default=None, help="torch threads (1 when two runs share 2 cores)")
    sub.add_parser("status", parents=[common], help="done / missing runs and the commands for the missing ones")
    s = sub.add_parser("score", parents=[common], help="score finished runs into the results JSON")
    s.add_argument("--workers", type=int, default=1)
    s.add_argument("--tta-row", default=None, choices=sorted(ROWS), help="TTA for this row (default: the best)")
    lat = sub.add_parser("latency", parents=[common], help="3D-side latency of each head, ratio to FastOcc")
    lat.add_argument("--preset", default="nano", choices=("nano", "tiny"),
                     help="nano = the trained rows' size; tiny = the paper's Table IV size")
    lat.add_argument("--repeats", type=int, default=5)
    lat.add_argument("--rounds", type=int, default=3, help="whole measurements; medians over them")
    lat.add_argument("--threads", type=int, default=None)
    st = sub.add_parser("steptime", parents=[common], help="training s/step of rows, one run at a time (idle machine)")
    st.add_argument("--rows", default="fastocc,3dfcn,deconv,hist0,hist16,hist16cached,hist0fuse",
                    help="comma-separated rows; ratios are to the first (default: %(default)s)")
    st.add_argument("--samples", type=int, default=40, help="training samples per timing epoch")
    st.add_argument("--rounds", type=int, default=2, help="interleaved rounds; medians over them")
    st.add_argument("--threads", type=int, default=1, help="torch threads (the trained rows used 1)")
    t = sub.add_parser("tables", parents=[common], help="write the markdown and PNGs from the results JSON")
    t.add_argument("--md", type=Path, default=DOCS / "ablations.md")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    store = args.store or load_config(RECIPE).store
    if args.cmd == "run":
        return run_row(args.row, args.seed, args.epochs, args.store, args.threads, args.runs_dir)
    if args.cmd == "status":
        status(args.epochs, args.store, args.runs_dir)
    elif args.cmd == "score":
        score(args.epochs, store, args.workers, args.runs_dir, args.results, args.tta_row)
    elif args.cmd == "steptime":
        rows = [r.strip() for r in args.rows.split(",") if r.strip()]
        if unknown := [r for r in rows if r not in ROWS]:
            raise SystemExit(f"unknown rows {unknown}; rows: {', '.join(ROWS)}")
        step_time(rows, args.samples, args.rounds, args.threads, args.store, args.runs_dir / "steptime",
                  args.results)
    elif args.cmd == "latency":
        latency(args.preset, args.repeats, args.rounds, args.threads, args.results)
    else:
        tables(args.results, args.md, args.epochs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
