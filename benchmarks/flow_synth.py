"""Flow end to end on a synthetic world: `occdata labels --grid openocc-v2` scored for mAVE / OccScore against
a truth store whose flow is the world's own motion (docs/labels.md "Flow", figures).

    python -m benchmarks.flow_synth --out /tmp/flow_synth [--scenes 2 --samples 6 --seed 11] [--json]

Steps: `occdata synth`; `occdata labels --grid openocc-v2` (with `--lidar-sweeps`); a truth tree in
OpenOcc v2's layout whose semantics are the world's own labels (`gts/`) and whose flow is, on each voxel an
actor wins, that actor's true velocity (`object_velocities`, rotated into key ego), 0 elsewhere; a store
from that tree (`occdata build --gts`), another from the generated labels; then `occdata eval` of the
generated labels against both (the second is the sanity check: mAVE 0).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from occdata.constants import FREE_LABEL, GRID
from occdata.geometry import invert_rigid
from occdata.gridfiles import LabelSite, write_grid_label
from occdata.grids import GRID_PRESETS
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.nuscenes import load_nuscenes
from occdata.occ3d import label_path, read_label
from occdata.synth import SynthConfig, synthesize
from occdata.synth.annotations import object_velocities
from occdata.synth.labels import CLASS_PRIORITY, primitives_to_frame, voxelize_primitives
from occdata.synth.pipeline import ego_transform, scene_world
from occdata.synth.world import place_parts

SPEC = GRID_PRESETS["openocc-v2"]


def truth_flow(world: Any, t_us: int, truth: np.ndarray) -> np.ndarray:
    """`(X, Y, Z, 2) float32`: each moving actor's true velocity (key ego, m/s) on the voxels it occupies
    whose truth class is its own (the actor won the voxel); 0 elsewhere."""
    T_global_from_keyego = ego_transform(world, t_us)
    R = invert_rigid(T_global_from_keyego)[:3, :3]
    v_all = object_velocities(world, t_us)[len(world.static_objects):] @ R.T  # the actors in the world, in order
    flow = np.zeros((*GRID.shape, 2), np.float32)
    lower = np.asarray(GRID.lower, np.float64)
    present = [a for a in world.actors if a.in_world(world.path, t_us)]
    for a, v in zip(present, v_all, strict=True):
        params = primitives_to_frame(place_parts(a.parts, *a.pose_at(world.path, t_us)), T_global_from_keyego)
        own = voxelize_primitives(np.full(GRID.shape, FREE_LABEL, np.uint8), params, a.cls.astype(np.int32),
                                  CLASS_PRIORITY, lower, GRID.voxel_size)
        won = (own != FREE_LABEL) & (truth == own)
        flow[won] = v[:2]
    return flow


def write_truth_tree(world_root: Path, out: Path, seed: int, n_samples: int) -> int:
    """The world's labels and true flow as an OpenOcc v2 tree under `out`; returns the keyframes written."""
    ds = load_nuscenes(world_root, None)
    n = 0
    for scene in ds.scenes:
        world = scene_world(seed, int(scene.name.rsplit("-", 1)[1]), n_samples)  # synth-0001 -> scene index 1
        for s in (x for x in ds.samples if x.scene_token == scene.token):
            labels = read_label(label_path(world_root / "gts", scene.name, s.token), require_masks=True)
            labels["flow"] = truth_flow(world, s.timestamp, labels["semantics"])
            site = LabelSite(scene.name, scene.token, s.token, s.lidar.token, s.lidar.path.name)
            write_grid_label(SPEC, out, site, labels)
            n += 1
    return n


def _eval(store: Path, pred: Path) -> dict[str, Any]:
    from occdata.eval.evaluate import EvalConfig, evaluate_predictions, results_dict

    out = {}
    for split in ("train", "val"):
        r = evaluate_predictions(EvalConfig(pred=pred, store=store, split=split, mask="none", progress=False,
                                            pred_classes="openocc-v2"))
        d = results_dict(r.miou, r.rayiou, n_samples=r.n_samples)
        out[split] = {k: d.get(k) for k in ("n_samples", "miou", "rayiou", "mave", "occ_score")}
        out[split]["ave"] = {c: row["ave"] for c, row in d["per_class"].items() if "ave" in row}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--samples", type=int, default=6)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    from occdata.store.build import BuildConfig, build_store

    world = synthesize(SynthConfig(out=args.out / "world", scenes=args.scenes, samples=args.samples, seed=args.seed,
                                   width=320, height=180, progress=False))
    gen = args.out / "labels"
    generate_labels(LabelsConfig(root=world, out=gen, options=LabelOptions(lidar_sweeps=True), progress=False,
                                 grids=(GRID_PRESETS["occ3d"], SPEC)))
    n = write_truth_tree(world, args.out / "truth", args.seed, args.samples)
    for name, gts in (("truth", args.out / "truth"), ("self", gen / "openocc-v2")):
        build_store(BuildConfig(root=world, out=args.out / f"{name}.zarr", gts=gts, progress=False))
    result = {"keyframes": n, "world": {"scenes": args.scenes, "samples": args.samples, "seed": args.seed},
              "generated_vs_truth": _eval(args.out / "truth.zarr", gen / "openocc-v2"),
              "generated_vs_itself": _eval(args.out / "self.zarr", gen / "openocc-v2")}
    print(json.dumps(result, indent=1) if args.json else result)


if __name__ == "__main__":
    main()
