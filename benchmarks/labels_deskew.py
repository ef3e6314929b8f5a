"""`occdata labels --deskew` on uncompensated clouds: a synthetic TruckScenes-like world written twice,
with compensated sweeps (every point at the sweep's instant) and with `occdata synth --uncompensated`
(each LiDAR turns over its 100 ms period, every point taken from the ego pose of its own time and
stamped with it). Each is labelled (keyframes, every LiDAR, one thread) with and without `--deskew` and
scored against the world's exact truth (`occdata.labels.score`): precision, surface recall, and the CPU
seconds of the labelling child.

    python -m benchmarks.labels_deskew [--seed 3,4 --samples 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

from benchmarks.bench_labels import generate
from benchmarks.common import write_json
from benchmarks.provenance import finish, machine
from occdata.labels.score import score_tree

__all__: list[str] = []


def run(seed: int, samples: int, work: Path) -> dict[str, Any]:
    """The four rows of one seed: world (compensated / uncompensated) x labels (plain / --deskew)."""
    from occdata.synth import SynthConfig, synthesize

    rows: dict[str, Any] = {}
    for world_name, uncompensated in (("compensated", False), ("uncompensated", True)):
        world = work / f"s{seed}_{world_name}"
        synthesize(SynthConfig(out=world, scenes=1, samples=samples, seed=seed, width=96, height=54, progress=False,
                               rig="truckscenes", uncompensated=uncompensated))
        for labels_name, extra in (("plain", []), ("deskew", ["--deskew"])):
            out = work / f"s{seed}_{world_name}_{labels_name}"
            cost = generate(world, out, extra)
            t = score_tree(world, out, world / "gts")
            rows[f"{world_name}/{labels_name}"] = {"precision": t.voxels.precision, "surface_recall": t.voxels.recall,
                                                   "cpu_seconds": cost["cpu_seconds"]}
            print(seed, world_name, labels_name, json.dumps({k: round(v, 4) for k, v in
                                                             rows[f"{world_name}/{labels_name}"].items()}), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", default="3,4", help="comma-separated world seeds")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    record = machine(samples=a.samples)
    with tempfile.TemporaryDirectory(prefix="labels_deskew_") as tmp:
        seeds = {s: run(int(s), a.samples, Path(tmp)) for s in a.seed.split(",")}
    result = finish({**record, "seeds": seeds})
    if a.json:
        write_json(result, a.json, indent=1)


if __name__ == "__main__":
    main()
