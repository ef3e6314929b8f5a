"""Flow end to end on a synthetic world: `occdata labels --grid openocc-v2` scored for mAVE / OccScore against
a truth store whose flow is the world's own motion (docs/labels.md "Flow", figures).

    python -m benchmarks.flow_synth --out /tmp/flow_synth [--scenes 2 --samples 6 --seed 11] [--json]

Steps: `occdata synth`; `occdata labels --grid openocc-v2` (with `--all-sweeps`); a truth tree in
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
from occdata.formats.gridfiles import LabelSite, write_grid_label
from occdata.formats.gridspec import GRID_PRESETS
from occdata.formats.occ3d import label_path, read_label
from occdata.geometry import invert_rigid
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.nuscenes import load_nuscenes
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
    """Per split: samples, mIoU and RayIoU (percent), mAVE (m/s, unrounded), OccScore (percent), AVE per
    moving class (m/s; None: no true-positive ray)."""
    from occdata.constants import CLASS_NAMES
    from occdata.eval.evaluate import EvalConfig, evaluate_predictions
    from occdata.eval.flow import MOVING_CLASSES

    out = {}
    for split in ("train", "val"):
        r = evaluate_predictions(EvalConfig(pred=pred, store=store, split=split, mask="none", progress=False,
                                            pred_classes="openocc-v2"))
        q = r.rayiou
        out[split] = {"n_samples": r.n_samples, "miou": round(100 * r.miou.miou, 2),
                      "rayiou": round(100 * q.rayiou, 2), "mave": float(f"{q.mave:.3g}"),
                      "occ_score": round(100 * q.occ_score, 2),
                      "ave": {CLASS_NAMES[c]: None if np.isnan(a) else float(f"{a:.3g}")
                              for c, a in ((c, q.ave_per_class[c]) for c in MOVING_CLASSES)}}
    return out


def zero_flow_copy(src: Path, dst: Path) -> Path:
    """The control: the same prediction files with their flow zeroed (mAVE = the truth's own speeds)."""
    for f in src.glob("*/*/labels.npz"):
        with np.load(f) as d:
            arrays = dict(d)
        arrays["flow"] = np.zeros_like(arrays["flow"])
        out = dst / f.relative_to(src)
        out.parent.mkdir(parents=True, exist_ok=True)
        np.savez(out, **arrays)
    return dst


def truth_speeds(tree: Path) -> dict[str, float]:
    sp = np.concatenate([np.linalg.norm(np.load(f)["flow"], axis=-1).ravel() for f in tree.glob("*/*/labels.npz")])
    moving = sp[sp >= 0.1]
    return {"moving_voxels": int(moving.size), "speed_median": round(float(np.median(moving)), 2),
            "speed_max": round(float(moving.max()), 2)}


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
    generate_labels(LabelsConfig(root=world, out=gen, options=LabelOptions(all_sweeps=True), progress=False,
                                 grids=(GRID_PRESETS["occ3d"], SPEC)))
    n = write_truth_tree(world, args.out / "truth", args.seed, args.samples)
    for name, gts in (("truth", args.out / "truth"), ("self", gen / "openocc-v2")):
        build_store(BuildConfig(root=world, out=args.out / f"{name}.zarr", gts=gts, progress=False))
    result = {"keyframes": n, "world": {"scenes": args.scenes, "samples": args.samples, "seed": args.seed},
              "truth_flow": truth_speeds(args.out / "truth"),
              "generated_vs_truth": _eval(args.out / "truth.zarr", gen / "openocc-v2"),
              "generated_vs_itself": _eval(args.out / "self.zarr", gen / "openocc-v2"),
              "zero_flow_control_vs_truth": _eval(args.out / "truth.zarr",
                                                  zero_flow_copy(gen / "openocc-v2", args.out / "zero_flow"))}
    print(json.dumps(result, indent=1) if args.json else result)


if __name__ == "__main__":
    main()
