"""Cross-check occdata.eval.metrics' RayIoU against the pure-python parts of SparseOcc's evaluation.

    python -m scripts.crosscheck_sparseocc --sparseocc PATH/TO/SparseOcc --store data.zarr \
        --label ../shared/data/occ3d-label/<token>/labels.npz [--json]

Needs a checkout of https://github.com/MCG-NJU/SparseOcc (not a dependency; its files are read at
run time, nothing of it is part of this project) and torch + pyquaternion to import it. Compared:
1. its `generate_lidar_rays()` vs `lidar_ray_directions()` (bitwise);
2. its `EgoPoseDataset` origins vs `scene_ray_origins` for every sample of the store (poses handed
   to it as quaternions, as nuScenes infos carry them);
3. its `calc_rayiou` counting on our per-ray (class, distance) outputs vs `RayIoUAccumulator`, for
   perturbed copies of a real label.
Its ray caster is a CUDA extension compiled at import (`loaders/ray_metrics.py` calls
`torch.utils.cpp_extension.load`), so only the functions above are taken from that file (parsed
with `ast`); the ray casting itself is checked in tests/test_metrics.py against brute-force marches.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import math
from pathlib import Path

import numpy as np


def _reference(sparseocc: Path) -> tuple[dict, type]:
    src = (sparseocc / "loaders" / "ray_metrics.py").read_text()
    ns: dict = {"np": np, "math": math}
    for node in ast.parse(src).body:
        if isinstance(node, ast.FunctionDef) and node.name in ("generate_lidar_rays", "calc_rayiou"):
            exec(compile(ast.Module([node], []), "sparseocc_ray_metrics", "exec"), ns)  # noqa: S102
    spec = importlib.util.spec_from_file_location("sparseocc_ego_pose", sparseocc / "loaders" / "ego_pose_dataset.py")
    mod = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return ns, mod.EgoPoseDataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sparseocc", type=Path, required=True, help="A SparseOcc checkout.")
    ap.add_argument("--store", type=Path, required=True, help="An occdata store (scenes of > 8 keyframes).")
    ap.add_argument("--label", type=Path, required=True, help="An Occ3D labels.npz (truth for step 3).")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from pyquaternion import Quaternion

    from occdata.constants import CLASS_NAMES, FREE_LABEL
    from occdata.eval.metrics import RayIoUAccumulator, first_hits, lidar_ray_directions
    from occdata.eval.rays import scene_ray_origins
    from occdata.store.reader import open_store

    ns, EgoPoseDataset = _reference(args.sparseocc)
    out: dict = {}

    ref_rays = ns["generate_lidar_rays"]()
    out["rays_bitwise_equal"] = bool(np.array_equal(ref_rays, lidar_ray_directions()))

    reader = open_store(args.store)
    T_g = reader.small("pose/T_global_from_keyego")
    T_el = reader.small("calib/T_ego_from_lidar")
    scene_of = reader.small("sample/scene_index")

    def quat(T: np.ndarray) -> list[float]:
        return Quaternion(matrix=T[:3, :3], atol=1e-6).elements.tolist()

    infos = [{"token": reader.token(i), "scene_name": reader.attrs["scenes"][int(scene_of[i])]["name"],
              "lidar2ego_translation": T_el[i, :3, 3].tolist(), "lidar2ego_rotation": quat(T_el[i]),
              "ego2global_translation": T_g[i, :3, 3].tolist(), "ego2global_rotation": quat(T_g[i])}
             for i in range(reader.n_samples)]
    ds = EgoPoseDataset(infos)
    worst, count_diff, counts = 0.0, 0, []
    for i in range(reader.n_samples):
        o_ref = ds[i][1].numpy()
        o = scene_ray_origins(reader, i)
        counts.append(len(o))
        if o.shape != o_ref.shape:
            count_diff += 1
            continue
        worst = max(worst, float(np.abs(o - o_ref).max()))
    out["origins"] = {"samples": reader.n_samples, "origin_count_differs": count_diff, "max_abs_diff_m": worst,
                      "origins_per_sample": np.bincount(counts).tolist()}

    rng = np.random.default_rng(0)
    with np.load(args.label, allow_pickle=False) as z:
        sem = z["semantics"]
    acc = RayIoUAccumulator()
    pcd_pred, pcd_gt = [], []
    for k in range(6):
        pred = np.roll(sem, k - 2, axis=0).copy()
        occ = np.flatnonzero(pred.ravel() != FREE_LABEL)
        flip = rng.choice(occ, occ.size // 20, replace=False)
        pred.reshape(-1)[flip] = rng.integers(0, FREE_LABEL, flip.size)
        origins = np.c_[rng.uniform(-30, 30, 5), rng.uniform(-5, 5, 5), np.full(5, 1.84)]
        acc.update(sem, pred, origins)
        gd, gc = first_hits(sem, origins)
        pd, pc = first_hits(pred, origins)
        # the reference's per-ray rows: (label, distance); no-hit distance is irrelevant (free never a TP)
        g = np.c_[gc.ravel().astype(np.float32), np.nan_to_num(gd.ravel(), nan=-1.0)]
        p = np.c_[pc.ravel().astype(np.float32), np.nan_to_num(pd.ravel(), nan=-1.0)]
        valid = g[:, 0].astype(np.int32) != FREE_LABEL
        pcd_gt.append(g[valid])
        pcd_pred.append(p[valid])
    ref_iou = np.array(ns["calc_rayiou"](pcd_pred, pcd_gt, list(CLASS_NAMES)))
    r = acc.result()
    out["counting"] = {
        "per_class_equal": bool(np.array_equal(np.nan_to_num(ref_iou, nan=-1), np.nan_to_num(r.per_class, nan=-1))),
        "rayiou_reference": float(np.nanmean(ref_iou)), "rayiou_ours": r.rayiou,
        "rayiou_at_reference": [float(np.nanmean(x)) for x in ref_iou], "rayiou_at_ours": list(r.rayiou_at.values()),
    }
    print(json.dumps(out, indent=2) if args.json else out)


if __name__ == "__main__":
    main()
