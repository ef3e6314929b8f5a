"""Benchmark `occdata labels` on a synthetic world whose exact labels are known.

For each variant (boxes vs the naive global-aggregation control; keyframes only vs + sweeps; with vs
without lidarseg) it generates the labels in a child process (seconds and peak RSS per scene), then
scores them against the world's truth: precision of the generated occupied voxels, recall of the
truth's observable surface (also its camera-visible part, and every camera-visible occupied voxel,
overall and per band of distance from the ego: 0-20, 20-40, 40+ m), semantic agreement, moving
instances' share of voxels inside their box, and `occdata eval` mIoU (camera mask) of the generated
labels as predictions, with its per-class IoU. `boxes-sweeps-densify` is `--densify`.

    python -m benchmarks.bench_labels [--scenes 1 --samples 40 --seed 11] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import write_json
from benchmarks.provenance import REPO, machine
from occdata.constants import CLASS_NAMES, FREE_LABEL
from occdata.eval.evaluate import EvalConfig, evaluate_predictions
from occdata.formats.gridspec import GRID_PRESETS, GridSpec
from occdata.labels.fidelity import BANDS
from occdata.labels.score import TreeScore, score_tree
from occdata.store.build import BuildConfig, build_store
from occdata.synth import SynthConfig, synthesize

__all__ = ["VARIANTS", "figures", "generate", "score", "without_lidarseg"]

VARIANTS = {  # name: (extra CLI options, drop lidarseg)
    "boxes-keyframes": ([], False),
    "boxes-sweeps": (["--all-sweeps"], False),
    "control-sweeps": (["--all-sweeps", "--boxes", "none", "--no-carve"], False),
    "boxes-sweeps-noseg": (["--all-sweeps"], True),
    "boxes-sweeps-densify": (["--all-sweeps", "--densify"], False),
    "control-sweeps-noseg": (["--all-sweeps", "--boxes", "none", "--no-carve"], True),
    # Every benchmark's grid from one aggregation (scored on the occ3d grid, which is the same)
    "boxes-sweeps-4grids": (["--all-sweeps", "--grid", "occ3d", "--grid", "openocc-v2", "--grid", "surroundocc",
                             "--grid", "openoccupancy"], False),
}


def generate(root: Path, out: Path, extra: list[str]) -> dict[str, float]:
    """Run `occdata labels` in a child on one core (NUMBA_NUM_THREADS=1); its wall and CPU seconds
    and peak RSS (MiB), from wait4. On a shared machine the CPU time is the per-core figure."""
    t0 = time.perf_counter()
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(root), "--out",
                             str(out), "--no-progress", *extra], cwd=REPO, env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"occdata labels failed ({proc.returncode})")
    return {"seconds": time.perf_counter() - t0, "cpu_seconds": usage.ru_utime + usage.ru_stime,
            "peak_rss_mib": usage.ru_maxrss / 1024}


def score(root: Path, gen: Path, truth: Path, spec: GridSpec = GRID_PRESETS["occ3d"]) -> dict[str, float]:
    """The fidelity figures on `spec` (Occ3D's grid, or an Occ3D-style custom one), overall and per
    distance band (`band_<lo>-<hi>_...`: precision, recall of the camera-visible observable surface,
    recall of every camera-visible occupied voxel)."""
    return figures(score_tree(root, gen, truth, spec))


def figures(t: TreeScore) -> dict[str, float]:
    """`score`'s figures from a `TreeScore`."""
    row = {"precision": t.voxels.precision, "surface_recall": t.voxels.recall,
           "visible_surface_recall": t.voxels.visible_surface_recall, "visible_recall": t.voxels.visible_recall,
           "semantic_agreement": t.voxels.semantic_agreement, "moving_inside": t.moving_fraction,
           "moving_inside_worst_instance": t.worst_instance, "moving_voxels": t.moving_total}
    for (lo, hi), band in zip(BANDS, t.bands, strict=True):
        name = f"band_{lo:g}-{hi:g}"
        row |= {f"{name}_precision": band.precision, f"{name}_visible_surface_recall": band.visible_surface_recall,
                f"{name}_visible_recall": band.visible_recall, f"{name}_visible_surface_voxels": band.visible_surface}
    return row


def without_lidarseg(root: Path, work: Path) -> Path:
    """`work/world_noseg`: the tree `root` without lidarseg (its data symlinked, the tables copied without
    lidarseg.json); made once."""
    src = work / "world_noseg"
    if not src.exists():
        src.mkdir()
        for p in root.iterdir():
            if p.name not in ("v1.0-mini", "lidarseg"):
                (src / p.name).symlink_to(p.resolve())
        shutil.copytree(root / "v1.0-mini", src / "v1.0-mini", ignore=shutil.ignore_patterns("lidarseg.json"))
    return src


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--samples", type=int, default=40)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated variant names")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    a = ap.parse_args()
    record = machine()
    work = a.keep or Path(tempfile.mkdtemp(prefix="bench_labels_"))
    root = work / "world"
    if not (root / "v1.0-mini").is_dir():
        synthesize(SynthConfig(out=root, scenes=a.scenes, samples=a.samples, seed=a.seed, width=a.width,
                               height=a.height, progress=False))
    store = work / "truth.zarr"
    if not store.exists():
        build_store(BuildConfig(root=root, out=store, gts=root / "gts", progress=False))
    rows = {}
    for name in a.variants.split(","):
        extra, no_seg = VARIANTS[name]
        src = without_lidarseg(root, work) if no_seg else root
        out = work / f"gen_{name}"
        shutil.rmtree(out, ignore_errors=True)
        cost = generate(src, out, extra)
        row = {**cost, "cpu_seconds_per_scene": cost["cpu_seconds"] / a.scenes, **score(root, out, root / "gts")}
        for split in ("train", "val") if a.scenes > 1 else ("train",):
            rep = evaluate_predictions(EvalConfig(pred=out, store=store, split=split, rayiou=False, progress=False))
            row[f"eval_miou_camera_{split}"] = float(rep.miou.miou)
            row |= {f"eval_iou_{CLASS_NAMES[c]}_{split}": float(v) for c, v in enumerate(rep.miou.per_class_iou)
                    if c != FREE_LABEL and np.isfinite(v)}
        rows[name] = row
        print(name, json.dumps({k: round(v, 4) for k, v in row.items()}), flush=True)
    result = {"machine": record, "world": vars(a) | {"json": None, "keep": None}, "rows": rows}
    if a.json:
        write_json(result, a.json, indent=1)


if __name__ == "__main__":
    main()
