"""`occdata labels` on the synthetic worlds of each rig (nuScenes, Lyft Level 5, MAN TruckScenes), scored
against each world's own exact truth as `benchmarks/bench_labels.py` scores nuScenes'.

Per rig and seed: `occdata synth --rig R` writes the world and its truth on two grids: Occ3D's (0.4 m,
x, y -40..40 m, z -1..5.4 m) and the truck grid `TRUCK_RANGE` (0.4 m, key ego, `gts/occ3d-0.4m/`). Then
`occdata labels --all-sweeps --voxel-size 0.4 --range TRUCK_RANGE` labels both grids in one aggregation
from every LiDAR of the rig ("all LiDARs"), and again from the reference LiDAR alone (`--lidars REF`,
"reference LiDAR"; rigs with more than one LiDAR), in a child on one thread. Each is scored on both
grids: precision, surface recall, semantic agreement, object semantic agreement, moving objects' voxels
inside their box (`occdata.labels.score`), and the true occupied voxels found.

The Lyft and TruckScenes worlds have no lidarseg (as the datasets' LiDAR has none), so a static point
is class 0 (others) and semantic agreement measures little beyond the objects: the nuScenes world is
labelled without its lidarseg too (`bench_labels.without_lidarseg`), so that the rigs are compared
like for like. `object_semantic_agreement`: on voxels the truth holds an object class (barrier ..
truck, the classes boxes give) and the labels hold occupied, the share of the same class.

    python -m benchmarks.labels_rigs [--rig nuscenes,lyft,truckscenes --seed 11,12 --samples 40] [--json out.json]
    python -m benchmarks.labels_rigs --table out.json   # the markdown tables of docs/labels.md "Other rigs"
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_labels import figures, generate, without_lidarseg
from benchmarks.common import write_json
from benchmarks.provenance import finish, machine
from occdata.constants import FREE_LABEL
from occdata.formats.gridfiles import read_grid_label
from occdata.formats.gridspec import GRID_PRESETS, GridSpec, custom_grid
from occdata.formats.occ3d import label_path
from occdata.labels.score import score_tree
from occdata.nuscenes import load_nuscenes
from occdata.synth import SynthConfig, synthesize
from occdata.synth.rig import RIGS

__all__ = ["OBJECT_CLASSES", "TRUCK_FRONT_M", "TRUCK_LENGTH_M", "TRUCK_RANGE", "TRUCK_VOXEL", "range_args",
           "truck_grid"]

# The truck grid (key ego: x forward from the tractor's rear axle, y left, z up from the road), chosen for
# an articulated truck rather than a car:
# - forward 80 m: a loaded 40 t truck at 80 km/h needs some 60-70 m to stop (1 s reaction + braking at
#   ~5 m/s^2), against Occ3D's 40 m; it is also the reach of the synthetic LiDARs (LIDAR_MAX_RANGE 80 m);
# - backward 40 m: the semi-trailer (TRUCK_LENGTH_M, EU limit, front bumper ~6 m ahead of the rear axle:
#   the tail ~10.5 m behind it) plus the ~30 m of traffic behind it that a lane change must watch;
# - sideways 40 m as Occ3D (two lanes and the kerb either side);
# - z -1..7 m: the truck is ~4 m tall with its roof LiDARs at 3.9 m (the synthetic rig); 7 m leaves 3 m
#   above the roof (bridges, gantries, signs over the lane), against Occ3D's 5.4 m.
# 300 x 200 x 20 voxels at 0.4 m: 1.2 M, 1.9x Occ3D's 0.64 M.
TRUCK_VOXEL = 0.4
TRUCK_RANGE = (-40.0, -40.0, -1.0, 80.0, 40.0, 7.0)
TRUCK_LENGTH_M = 16.5  # an EU articulated vehicle's maximum length
TRUCK_FRONT_M = 6.0  # front bumper ahead of the rear axle (the front LiDAR sits at 5.6 m)
OBJECT_CLASSES = tuple(range(1, 11))  # barrier .. truck: what boxes label


def truck_grid() -> GridSpec:
    """The truck grid as `occdata labels|synth --voxel-size 0.4 --range TRUCK_RANGE` makes it."""
    return custom_grid(TRUCK_VOXEL, TRUCK_RANGE[:3], TRUCK_RANGE[3:])


def range_args() -> list[str]:
    """`--voxel-size 0.4 --range ...` of the truck grid."""
    return ["--voxel-size", f"{TRUCK_VOXEL:g}", "--range", *(f"{v:g}" for v in TRUCK_RANGE)]


def object_semantics(root: Path, gen: Path, truth: Path, spec: GridSpec) -> tuple[int, int]:
    """`(same class, total)`: voxels the truth holds an object class in and the labels hold occupied."""
    ds = load_nuscenes(root, None)
    same = total = 0
    for sc in ds.scenes:
        for tok in sc.sample_tokens:
            g, t = (read_grid_label(spec, label_path(d, sc.name, tok))["semantics"] for d in (gen, truth))
            both = np.isin(t, OBJECT_CLASSES) & (g != FREE_LABEL)
            same += int((both & (g == t)).sum())
            total += int(both.sum())
    return same, total


def _grid_figures(root: Path, gen: Path, truth: Path, spec: GridSpec, prefix: str) -> dict[str, float]:
    t = score_tree(root, gen, truth, spec)
    out: dict[str, float] = {k: v for k, v in figures(t).items() if k != "visible_recall"}
    out |= {"generated_voxels": t.voxels.generated, "true_occupied_found": t.voxels.true_positive,
            "surface_voxels": t.voxels.surface}
    same, total = object_semantics(root, gen, truth, spec)
    out |= {"object_semantic_agreement": same / max(total, 1), "object_voxels_found": total}
    return {f"{prefix}{k}": v for k, v in out.items()}


def run_rig(rig: str, seed: int, a: argparse.Namespace, work: Path) -> dict[str, dict[str, Any]]:
    """The rows of one rig's world: variant -> figures."""
    spec = truck_grid()
    root = work / f"{rig}-{seed}" / "world"
    if not (root / RIGS[rig].version).is_dir():
        synthesize(SynthConfig(out=root, scenes=a.scenes, samples=a.samples, seed=seed, width=a.width,
                               height=a.height, progress=False, rig=rig, grids=(spec,)))
    src = without_lidarseg(root, root.parent) if rig == "nuscenes" else root
    ds = load_nuscenes(root, None)
    variants = {"all-lidars": []}
    if len(ds.rig.lidars) > 1:
        variants["reference-lidar"] = ["--lidars", ds.rig.reference_lidar]
    rows = {}
    for name, extra in variants.items():
        out = root.parent / f"gen_{name}"
        shutil.rmtree(out, ignore_errors=True)
        cost = generate(src, out, ["--all-sweeps", "--grid", "occ3d", *range_args(), *extra])
        keyframes = len(ds.samples)
        row: dict[str, Any] = {"rig": rig, "seed": seed, "lidars": list(ds.rig.lidars) if not extra else [extra[1]],
                               "keyframes": keyframes, **cost, "cpu_ms_per_keyframe": 1e3 * cost["cpu_seconds"] /
                               keyframes}
        row |= _grid_figures(root, out, root / "gts", GRID_PRESETS["occ3d"], "")
        row |= _grid_figures(root, out / spec.name, root / "gts" / spec.name, spec, "truck_grid_")
        rows[f"{rig}/seed{seed}/{name}"] = row
        print(f"{rig}/seed{seed}/{name}", json.dumps({k: round(v, 4) if isinstance(v, float) else v
                                                      for k, v in row.items() if "band_" not in k}), flush=True)
    return rows


_COLUMNS = (  # (heading, key, format)
    ("precision", "precision", "{:.4f}"), ("surface recall", "surface_recall", "{:.3f}"),
    ("object semantic agreement", "object_semantic_agreement", "{:.3f}"),
    ("semantic agreement (all)", "semantic_agreement", "{:.3f}"),
    ("moving in box (worst)", "moving_inside", "{:.3f}"), ("true occupied voxels found", "true_occupied_found", "{:,}"),
)


def table(result: dict[str, Any], prefix: str = "") -> str:
    """A markdown table of `result["rows"]` (one line per rig and variant, the seeds side by side as
    `a / b`), on Occ3D's grid (`prefix` "") or the truck grid ("truck_grid_")."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for key, row in result["rows"].items():
        groups.setdefault((row["rig"], key.rsplit("/", 1)[1]), []).append(row)
    seeds = sorted({row["seed"] for row in result["rows"].values()})
    head = ["rig", "LiDARs", *(c[0] for c in _COLUMNS), "labels CPU ms / keyframe"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (rig, variant), rows in groups.items():
        rows = sorted(rows, key=lambda r: r["seed"])

        def cell(key: str, fmt: str, rows: list[dict[str, Any]] = rows) -> str:
            return " / ".join(fmt.format(r[key]) for r in rows)

        cells = [cell(prefix + k, f) for _, k, f in _COLUMNS]
        cells[4] += " (" + cell(prefix + "moving_inside_worst_instance", "{:.3f}") + ")"
        lidars = rows[0]["lidars"]
        who = f"{len(lidars)}: all" if variant == "all-lidars" else f"1: {lidars[0]} alone"
        lines.append(f"| {rig} | {who} | " + " | ".join(cells) + f" | {cell('cpu_ms_per_keyframe', '{:.0f}')} |")
    return f"seeds {' / '.join(map(str, seeds))}\n\n" + "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rig", default="nuscenes,lyft,truckscenes", help="comma-separated rigs of `occdata synth`")
    ap.add_argument("--seed", default="11", help="comma-separated world seeds")
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--samples", type=int, default=20)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--json", type=Path, default=None, help="written after every rig (a partial run keeps its rows)")
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    ap.add_argument("--table", type=Path, default=None, help="print the tables of a result file and stop")
    a = ap.parse_args()
    if a.table:
        result = json.loads(a.table.read_text())
        print("Occ3D's grid:", table(result), "", "Truck grid:", table(result, "truck_grid_"), sep="\n")
        return
    rigs, seeds = a.rig.split(","), [int(s) for s in a.seed.split(",")]
    unknown = sorted(set(rigs) - set(RIGS))
    if unknown:
        raise SystemExit(f"unknown rig(s) {unknown}; choose from {sorted(RIGS)}")
    record = machine()
    work = a.keep or Path(tempfile.mkdtemp(prefix="labels_rigs_"))
    spec = truck_grid()
    result: dict[str, Any] = {
        "machine": record, "world": vars(a) | {"json": None, "keep": None},
        "grids": {"occ3d": GRID_PRESETS["occ3d"].describe() | {"classes": None, "from_occ3d": None},
                  "truck_grid": spec.describe() | {"classes": None, "from_occ3d": None}},
        "rows": {},
    }
    for seed in seeds:
        for rig in rigs:
            result["rows"] |= run_rig(rig, seed, a, work)
            if a.json:
                finish(record)
                write_json(result, a.json, indent=1)
    if a.keep is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
