"""`occdata labels` without boxes (free-space carving, issue 39), measured three ways.

- `synth`: a synthetic world with moving actors (`occdata synth`), labelled with its boxes (the
  box-aware run), with them withheld (`--boxes none`, carving), naively (`--boxes none --no-carve`:
  every point static) and with carving on top of the boxes (`--carve`), each with and without
  lidarseg. Scored against the world's exact truth: precision, static precision (voxels outside every
  box at that keyframe), surface recall, and the share of the moving actors' swept path (their boxes
  over the scene less every box at the keyframe, truth-free voxels) that is occupied.
- `real`: real scene-0916 (boxes, no lidarseg, keyframes only) with boxes withheld against the
  box-aware run: agreement on the box-aware run's static voxels (outside every box), and how much of
  the naive run's smear (occupied path voxels that the box-aware run has free) is gone.
- `lyft`: the real Lyft keyframes (3 LiDARs, no boxes): naive vs carved, a picture at one keyframe
  and the share of each keyframe's occupied voxels that its own rays (every LiDAR) crossed.

Every run is a child `occdata labels` on one thread (CPU seconds, peak RSS from wait4).

    python -m benchmarks.labels_carve --part synth [--samples 40 --seed 11 --sweeps] --json out.json
    python -m benchmarks.labels_carve --part real --json out.json
    python -m benchmarks.labels_carve --part lyft --pictures docs/img --json out.json
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
from benchmarks.common import SHARED_DATA, write_json
from benchmarks.provenance import machine
from occdata.constants import FREE_LABEL, GRID
from occdata.geometry import invert_rigid, transform_points
from occdata.labels.fidelity import Fidelity, _box_voxels, swept_path, voxel_fidelity
from occdata.nuscenes import load_lidar_points, load_nuscenes
from occdata.nuscenes.annotations import load_annotations, moving_instances
from occdata.visibility import lidar_mask

__all__: list[str] = []

SYNTH_VARIANTS = {  # name: (extra options, drop lidarseg)
    "boxes": ([], False),
    "carve": (["--boxes", "none"], False),
    "naive": (["--boxes", "none", "--no-carve"], False),
    "boxes+carve": (["--carve"], False),
    "boxes-noseg": ([], True),
    "carve-noseg": (["--boxes", "none"], True),
    "naive-noseg": (["--boxes", "none", "--no-carve"], True),
}


def _load(out: Path, scene: str, tok: str) -> dict[str, np.ndarray]:
    with np.load(out / scene / tok / "labels.npz", allow_pickle=False) as z:
        return {k: z[k].copy() for k in z.files}


def _noseg_copy(root: Path, work: Path) -> Path:
    """The tree without lidarseg: data symlinked, tables copied without lidarseg.json."""
    src = work / "world_noseg"
    if not src.exists():
        src.mkdir()
        version = next(p.name for p in root.iterdir() if p.name.startswith("v1.0"))
        for p in root.iterdir():
            if p.name not in (version, "lidarseg"):
                (src / p.name).symlink_to(p.resolve())
        shutil.copytree(root / version, src / version, ignore=shutil.ignore_patterns("lidarseg.json"))
    return src


def _outside_boxes(boxes: list, T: np.ndarray) -> np.ndarray:
    """`(X, Y, Z) bool`: voxels outside every box of a keyframe (each grown by one voxel)."""
    inside = np.zeros(GRID.shape, bool)
    for b in boxes:
        inside |= _box_voxels(T @ b.T_global_from_box(), b.size_wlh, 1)
    return ~inside


def _score(root: Path, gen: Path, reference: Path, truth: bool) -> dict[str, float]:
    """Against `reference` (the truth with `truth`, else the box-aware run): precision (truth only),
    static precision / agreement outside every box, surface recall (truth only), swept-path smear."""
    ds = load_nuscenes(root, None)
    ann = load_annotations(root, ds.version)
    total, static = Fidelity(), Fidelity()
    wrong = free = agree = ref_static = gen_static = 0
    for sc in ds.scenes:
        boxes = [list(ann.boxes_by_sample.get(t, ())) for t in sc.sample_tokens]
        movers = moving_instances(boxes)
        for n, tok in enumerate(sc.sample_tokens):
            T = invert_rigid(ds.sample(tok).T_global_from_keyego)
            g = _load(gen, sc.name, tok)["semantics"]
            ref = _load(reference, sc.name, tok)
            out = _outside_boxes(boxes[n], T)
            if truth:
                total.add(voxel_fidelity(g, ref["semantics"], ref["mask_lidar"]))
                static.add(voxel_fidelity(g, ref["semantics"], ref["mask_lidar"], region=out))
            occ_ref, occ_gen = (ref["semantics"] != FREE_LABEL) & out, (g != FREE_LABEL) & out
            agree += int((occ_ref & occ_gen).sum())
            ref_static += int(occ_ref.sum())
            gen_static += int(occ_gen.sum())
            w, f = swept_path(g, ref["semantics"] == FREE_LABEL, T, boxes, n, movers)
            wrong += w
            free += f
    row = {"static_agreement_recall": agree / max(ref_static, 1),
           "static_agreement_precision": agree / max(gen_static, 1), "static_voxels": gen_static,
           "path_wrong": wrong, "path_free": free, "path_wrong_share": wrong / max(free, 1)}
    if truth:
        row |= {"precision": total.precision, "surface_recall": total.recall, "static_precision": static.precision,
                "static_surface_recall": static.recall}
    return row


def _run(root: Path, out: Path, extra: list[str], keyframes: int) -> dict[str, float]:
    shutil.rmtree(out, ignore_errors=True)
    cost = generate(root, out, extra)
    return {**cost, "cpu_seconds_per_keyframe": cost["cpu_seconds"] / keyframes}


def _removed(rows: dict[str, dict[str, float]], carved: str, naive: str) -> float:
    return 1.0 - rows[carved]["path_wrong"] / max(rows[naive]["path_wrong"], 1)


def synth_part(a: argparse.Namespace, work: Path) -> dict[str, object]:
    from occdata.synth import SynthConfig, synthesize

    root = work / "world"
    if not (root / "v1.0-mini").is_dir():
        synthesize(SynthConfig(out=root, scenes=1, samples=a.samples, seed=a.seed, width=320, height=180,
                               progress=False))
    sweeps = ["--all-sweeps"] if a.sweeps else []
    rows: dict[str, dict[str, float]] = {}
    for name in a.variants.split(","):
        extra, noseg = SYNTH_VARIANTS[name]
        src = _noseg_copy(root, work) if noseg else root
        rows[name] = _run(src, work / f"gen_{name}", [*sweeps, *extra], a.samples)
        rows[name] |= _score(root, work / f"gen_{name}", root / "gts", truth=True)
        print(name, json.dumps({k: round(v, 4) for k, v in rows[name].items()}), flush=True)
    for suffix in ("", "-noseg"):
        if f"carve{suffix}" in rows and f"naive{suffix}" in rows:
            rows[f"carve{suffix}"]["smear_removed_vs_naive"] = _removed(rows, f"carve{suffix}", f"naive{suffix}")
    return {"world": {"samples": a.samples, "seed": a.seed, "sweeps": a.sweeps}, "rows": rows}


def real_part(a: argparse.Namespace, work: Path) -> dict[str, object]:
    root = a.root or SHARED_DATA / "nuscenes-real-seq"
    n = len(load_nuscenes(root, None).samples)
    rows: dict[str, dict[str, float]] = {}
    for name, extra in {"boxes": [], "carve": ["--boxes", "none"], "naive": ["--boxes", "none", "--no-carve"],
                        "boxes+carve": ["--carve"]}.items():
        rows[name] = _run(root, work / f"gen_{name}", extra, n)
    for name in rows:
        rows[name] |= _score(root, work / f"gen_{name}", work / "gen_boxes", truth=False)
        print(name, json.dumps({k: round(v, 4) for k, v in rows[name].items()}), flush=True)
    rows["carve"]["smear_removed_vs_naive"] = _removed(rows, "carve", "naive")
    for spec in a.carve_options:  # the evidence rule's trade-off (library call: the CLI has no such options)
        from occdata.labels import LabelOptions, LabelsConfig, generate_labels
        from occdata.labels.carve import CarveOptions

        name = f"carve {spec}"
        out = work / f"gen_carve_{len(rows)}"
        shutil.rmtree(out, ignore_errors=True)
        opts = LabelOptions(use_boxes=False, carve=True, carve_options=CarveOptions(**json.loads(spec)))
        generate_labels(LabelsConfig(root=root, out=out, options=opts, progress=False))
        rows[name] = _score(root, out, work / "gen_boxes", truth=False)
        rows[name]["smear_removed_vs_naive"] = 1.0 - rows[name]["path_wrong"] / max(rows["naive"]["path_wrong"], 1)
        print(name, json.dumps({k: round(v, 4) for k, v in rows[name].items()}), flush=True)
    return {"root": str(root), "rows": rows}


def _own_ray_share(root: Path, gen: Path) -> list[float]:
    """Per keyframe: the share of its occupied voxels that its own rays (every LiDAR, from each one's
    origin) passed through without ending there: space it saw empty at that time."""
    ds = load_nuscenes(root, None)
    shares = []
    for s in ds.samples:
        sem = _load(gen, s.scene_name, s.token)["semantics"]
        T_key_from_global = invert_rigid(s.T_global_from_keyego)
        crossed = np.zeros(GRID.shape, bool)
        for rec in s.lidars:
            pts = load_lidar_points(rec.path)[:, :3].astype(np.float64)
            ends = transform_points(T_key_from_global @ rec.T_global_from_ego @ rec.T_ego_from_lidar, pts)
            origin = transform_points(T_key_from_global @ rec.T_global_from_ego, rec.T_ego_from_lidar[:3, 3][None])[0]
            # voxels the rays crossed, less those they ended in (a ray cut 0.4 m short of its return)
            d = ends - origin
            length = np.linalg.norm(d, axis=1, keepdims=True)
            short = origin + d * np.clip(1 - 0.4 / np.maximum(length, 1e-9), 0, 1)
            empty = np.full(GRID.shape, FREE_LABEL, np.uint8)
            crossed |= lidar_mask(empty, np.broadcast_to(origin, short.shape), short, np.asarray(GRID.lower),
                                  GRID.voxel_size) != 0
            idx = np.floor((ends - np.asarray(GRID.lower)) / GRID.voxel_size).astype(int)
            ok = ((idx >= 0) & (idx < np.array(GRID.shape))).all(axis=1)
            crossed[tuple(idx[ok].T)] = False
        occ = sem != FREE_LABEL
        shares.append(float((occ & crossed).sum() / max(occ.sum(), 1)))
    return shares


def lyft_part(a: argparse.Namespace, work: Path) -> dict[str, object]:
    from occdata.view.render import prediction_picture

    root = a.root or SHARED_DATA / "lyft-real"
    ds = load_nuscenes(root, None)
    n = len(ds.samples)
    rows: dict[str, dict[str, object]] = {}
    for name, extra in {"carve": [], "naive": ["--no-carve"]}.items():
        rows[name] = _run(root, work / f"gen_{name}", extra, n)
        shares = _own_ray_share(root, work / f"gen_{name}")
        occupied = [int((_load(work / f"gen_{name}", s.scene_name, s.token)["semantics"] != FREE_LABEL).sum())
                    for s in ds.samples]
        rows[name] |= {"own_rays_crossed_share": shares, "own_rays_crossed_mean": float(np.mean(shares)),
                       "occupied_voxels_mean": float(np.mean(occupied))}
        print(name, json.dumps({k: v for k, v in rows[name].items() if k != "own_rays_crossed_share"}), flush=True)
    if a.pictures:
        a.pictures.mkdir(parents=True, exist_ok=True)
        s = ds.samples[a.keyframe]
        naive, carved = (_load(work / f"gen_{k}", s.scene_name, s.token) for k in ("naive", "carve"))
        # No camera images: the real data stay out of the repository.
        pic = prediction_picture([], naive["semantics"], carved["semantics"], carved["mask_camera"], width=1200,
                                 title=f"Lyft keyframe {a.keyframe}, 3 LiDARs, no boxes; black static, blue dynamic",
                                 names=("naive: every point static", "carved by the scene's own rays"))
        path = a.pictures / f"labels_carve_lyft_k{a.keyframe:02d}.png"
        cv2.imwrite(str(path), pic[:, :, ::-1])
        print("wrote", path)
    return {"root": str(root), "keyframe_pictured": a.keyframe, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("synth", "real", "lyft"), required=True)
    ap.add_argument("--root", type=Path, default=None, help="real tree (default: the shared data)")
    ap.add_argument("--samples", type=int, default=40)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--sweeps", action="store_true", help="synth: with --lidar-sweeps")
    ap.add_argument("--variants", default=",".join(SYNTH_VARIANTS))
    ap.add_argument("--keyframe", type=int, default=8, help="lyft: the keyframe to draw")
    ap.add_argument("--carve-options", nargs="*", default=[], metavar="JSON",
                    help='real: also carve with these CarveOptions, e.g. \'{"min_frames": 3, "ratio": 2}\'')
    ap.add_argument("--pictures", type=Path, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="labels_carve_"))
    work.mkdir(parents=True, exist_ok=True)
    part = {"synth": synth_part, "real": real_part, "lyft": lyft_part}[a.part](a, work)
    result = {"machine": machine(), "part": a.part, **part}
    if a.json:
        write_json(result, a.json, indent=1)


if __name__ == "__main__":
    main()
