"""Semantics without lidarseg (issue 46): ground from geometry and classes from 2D image masks, measured
on a synthetic world against its exact truth.

The world (`occdata synth --image-masks`) is labelled without lidarseg and with its boxes withheld
(`--boxes none`: carving), with every sweep, five ways:

- `plain`: the old labels (`--ground-class 0`): every static point `others`;
- `ground`: ground from geometry (the default, class 11);
- `masks`: `--image-masks` with the truth masks;
- `masks-shift<s>`: with the masks degraded as a segmenter errs (each image shifted by up to `s` px in
  x and y, for each `s` of `--shifts`, so every boundary moves, and `--wrong` of its pixels given a
  random class); the images are 320 px wide, so 1 px here is 5 px of a 1600 px nuScenes image;
- and the box path without lidarseg, without and with the clean masks (`boxes`, `boxes+masks`): the
  cost of painting against the box path.

Scored on voxels occupied in both the labels and the truth: semantic accuracy, precision (occupied
voxels that the truth has occupied), and for the ground: the truth's flat voxels (classes 11-14)
labelled flat, and its other occupied voxels labelled flat. Every run is a child `occdata labels` on
one thread (CPU seconds, peak RSS from wait4).

    python -m benchmarks.labels_paint --seed 11 --samples 12 --json docs/results/labels_paint_s11.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from benchmarks.bench_labels import generate
from benchmarks.common import write_json
from benchmarks.labels_carve import _noseg_copy
from benchmarks.provenance import machine
from occdata.constants import FREE_LABEL
from occdata.nuscenes import load_nuscenes
from occdata.visibility import GROUND_CLASSES

__all__: list[str] = []

FLAT = np.array(GROUND_CLASSES)


def degrade(src: Path, dst: Path, shift: int, wrong: float, seed: int) -> None:
    """Every mask PNG under `src` written under `dst` (same layout) shifted by a random (dx, dy) in
    [-shift, shift] px (edges repeated) and with a `wrong` share of its pixels set to a random class 0-16."""
    rng = np.random.default_rng(seed)
    for path in sorted(src.rglob("*.png")):
        ids = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        dx, dy = rng.integers(-shift, shift + 1, 2)
        M = np.float32([[1, 0, dx], [0, 1, dy]])
        out = cv2.warpAffine(ids, M, (ids.shape[1], ids.shape[0]), flags=cv2.INTER_NEAREST,
                             borderMode=cv2.BORDER_REPLICATE)
        flip = rng.random(ids.shape) < wrong
        out[flip] = rng.integers(0, 17, int(flip.sum()))
        target = dst / path.relative_to(src)
        target.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(target), out)


def score(root: Path, gen: Path) -> dict[str, float]:
    """Against the world's truth (gts/), over voxels occupied in both (and within the truth's camera mask)."""
    ds = load_nuscenes(root, None)
    n = {k: 0 for k in ("gen", "both", "same", "both_cam", "same_cam", "flat", "flat_found", "other",
                        "other_flat", "flat_cam", "flat_found_cam")}
    for s in ds.samples:
        with np.load(root / "gts" / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            truth, cam = z["semantics"], z["mask_camera"] != 0
        with np.load(gen / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            g = z["semantics"]
        occ, t_occ = g != FREE_LABEL, truth != FREE_LABEL
        both = occ & t_occ
        t_flat = both & np.isin(truth, FLAT)
        g_flat = np.isin(g, FLAT)
        n["gen"] += int(occ.sum())
        n["both"] += int(both.sum())
        n["same"] += int((both & (g == truth)).sum())
        n["both_cam"] += int((both & cam).sum())
        n["same_cam"] += int((both & cam & (g == truth)).sum())
        n["flat"] += int(t_flat.sum())
        n["flat_found"] += int((t_flat & g_flat).sum())
        n["flat_cam"] += int((t_flat & cam).sum())
        n["flat_found_cam"] += int((t_flat & cam & g_flat).sum())
        n["other"] += int((both & ~np.isin(truth, FLAT)).sum())
        n["other_flat"] += int((both & ~np.isin(truth, FLAT) & g_flat).sum())
    return {"precision": n["both"] / max(n["gen"], 1), "semantic_accuracy": n["same"] / max(n["both"], 1),
            "semantic_accuracy_camera": n["same_cam"] / max(n["both_cam"], 1),
            "flat_labelled_flat": n["flat_found"] / max(n["flat"], 1),
            "other_labelled_flat": n["other_flat"] / max(n["other"], 1), "voxels_both": n["both"]}


def per_class(root: Path, gen: Path) -> dict[str, float]:
    """Per truth class, the share of its voxels occupied in both that carry its class."""
    ds = load_nuscenes(root, None)
    hit, tot = np.zeros(18), np.zeros(18)
    for s in ds.samples:
        with np.load(root / "gts" / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            truth = z["semantics"]
        with np.load(gen / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            g = z["semantics"]
        both = (g != FREE_LABEL) & (truth != FREE_LABEL)
        tot += np.bincount(truth[both], minlength=18)
        hit += np.bincount(truth[both & (g == truth)], minlength=18)
    return {str(c): round(float(hit[c] / tot[c]), 4) for c in range(17) if tot[c] > 0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=12)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--shifts", default="1,2", help="px: the degraded masks' largest boundary shifts, one run each")
    ap.add_argument("--wrong", type=float, default=0.03, help="the degraded masks' share of wrong pixels")
    ap.add_argument("--no-sweeps", dest="sweeps", action="store_false")
    ap.add_argument("--variants", default=None, help="default: plain,ground,masks,masks-shift<s>...,boxes,boxes+masks")
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="labels_paint_"))
    work.mkdir(parents=True, exist_ok=True)
    from occdata.synth import SynthConfig, synthesize

    root = work / "world"
    if not (root / "v1.0-mini").is_dir():
        synthesize(SynthConfig(out=root, scenes=1, samples=a.samples, seed=a.seed, width=320, height=180,
                               progress=False, image_masks=root / "masks"))
    shifts = [int(x) for x in a.shifts.split(",")]
    for shift in shifts:
        if not (work / f"masks_shift{shift}").is_dir():
            degrade(root / "masks", work / f"masks_shift{shift}", shift, a.wrong, a.seed)
    src = _noseg_copy(root, work)
    sweeps = ["--all-sweeps"] if a.sweeps else []
    variants = {
        "plain": ["--boxes", "none", "--ground-class", "0"],
        "ground": ["--boxes", "none"],
        "masks": ["--boxes", "none", "--image-masks", str(root / "masks")],
        **{f"masks-shift{s}": ["--boxes", "none", "--image-masks", str(work / f"masks_shift{s}")] for s in shifts},
        "boxes": [],
        "boxes+masks": ["--image-masks", str(root / "masks")],
    }
    rows: dict[str, dict[str, object]] = {}
    for name in (a.variants.split(",") if a.variants else variants):
        out = work / f"gen_{name}"
        shutil.rmtree(out, ignore_errors=True)
        cost = generate(src, out, [*sweeps, *variants[name]])
        rows[name] = {**cost, "cpu_seconds_per_keyframe": cost["cpu_seconds"] / a.samples, **score(root, out),
                      "per_class_accuracy": per_class(root, out)}
        print(name, json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in rows[name].items()
                                if k != "per_class_accuracy"}), flush=True)
    if "boxes" in rows and "boxes+masks" in rows:
        rows["boxes+masks"]["painting_cpu_seconds_per_keyframe"] = (
            rows["boxes+masks"]["cpu_seconds_per_keyframe"] - rows["boxes"]["cpu_seconds_per_keyframe"])
    result = {"machine": machine(), "world": {"samples": a.samples, "seed": a.seed, "sweeps": a.sweeps,
                                              "size": [320, 180], "shifts_px": shifts, "wrong": a.wrong},
              "rows": rows}
    if a.json:
        write_json(result, a.json, indent=1)


if __name__ == "__main__":
    main()
