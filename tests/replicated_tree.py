"""A multi-scene nuScenes-format tree made by replaying the real keyframe (tests only).

Every sample reuses the real sensor files (linked, never copied) and the real calibration; each
sample's 7 ego poses are shifted by the same rigid offset, so projections stay exact while poses
differ. Labels: the real Occ3D label file linked under gts/<scene>/<sample>/labels.npz.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path


def _tok(*parts: object) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def make_replicated_tree(
    real_root: Path, label_file: Path, out: Path, n_scenes: int = 2, n_samples: int = 5, labels: bool = True,
    boxes: int = 0, other_rows: int = 0,
) -> Path:
    """`n_scenes` scenes of `n_samples` replays each under `out`; with `boxes`, that many tracked
    objects per scene, one sample_annotation row each per sample (for the tables' size, not a scene's
    truth: fixed boxes beside the road, moving 1 m per sample); with `other_rows`, that many more
    sample_data rows per sample, each with its ego_pose row, that no command keeps (non-keyframe camera
    rows, unlinked: nuScenes has ~70 such rows a keyframe, camera sweeps at 12 Hz and radars), for the
    tables' size."""
    real_root, label_file = real_root.resolve(), label_file.resolve()
    src = real_root / "v1.0-mini"
    tables = {t: json.loads((src / f"{t}.json").read_text()) for t in (
        "attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
        "sample_annotation", "sample_data", "scene", "sensor", "visibility")}
    (base_sample,) = tables["sample"]
    base_sd = [sd for sd in tables["sample_data"] if sd["sample_token"] == base_sample["token"]]
    pose_of = {p["token"]: p for p in tables["ego_pose"]}
    scenes, samples, sds, poses = [], [], [], []
    for si in range(n_scenes):
        name = f"replay-{si:04d}"
        tokens = [_tok(name, k) for k in range(n_samples)]
        scenes.append({
            "token": _tok("scene", name), "log_token": tables["log"][0]["token"], "nbr_samples": n_samples,
            "name": name, "description": f"replayed real keyframe split={'val' if si == n_scenes - 1 else 'train'}",
            "first_sample_token": tokens[0], "last_sample_token": tokens[-1],
        })
        for k, tok in enumerate(tokens):
            dt = 500_000 * (k + 20 * si)
            samples.append({
                "token": tok, "timestamp": base_sample["timestamp"] + dt, "scene_token": scenes[-1]["token"],
                "prev": tokens[k - 1] if k else "", "next": tokens[k + 1] if k + 1 < n_samples else "",
            })
            for sd in base_sd:
                pose = dict(pose_of[sd["ego_pose_token"]])
                pose["token"] = _tok("pose", tok, sd["token"])
                pose["translation"] = [pose["translation"][0] + 4.0 * k, pose["translation"][1] + 100.0 * si, 0.0]
                pose["timestamp"] = pose["timestamp"] + dt
                poses.append(pose)
                sds.append({**sd, "token": _tok("sd", tok, sd["token"]), "sample_token": tok,
                            "ego_pose_token": pose["token"], "timestamp": sd["timestamp"] + dt})
            cams = [sd for sd in sds[-len(base_sd):] if sd["fileformat"] == "jpg"]
            for j in range(other_rows if cams else 0):
                sd = cams[j % len(cams)]
                pose = {**poses[-len(base_sd)], "token": _tok("pose-other", tok, j),
                        "timestamp": sd["timestamp"] + 1000 * (j + 1)}
                poses.append(pose)
                sds.append({**sd, "token": _tok("sd-other", tok, j), "ego_pose_token": pose["token"],
                            "timestamp": pose["timestamp"], "is_key_frame": False, "prev": "", "next": ""})
            if labels:
                label_dir = out / "gts" / name / tok
                label_dir.mkdir(parents=True, exist_ok=True)
                (label_dir / "labels.npz").symlink_to(label_file)
    tables.update(scene=scenes, sample=samples, sample_data=sds, ego_pose=poses)
    if boxes:
        tables["instance"], tables["sample_annotation"] = _boxes(scenes, samples, tables["category"], n_samples,
                                                                 boxes)
    vdir = out / "v1.0-mini"
    vdir.mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (vdir / f"{name}.json").write_text(json.dumps(rows))
    for f in (real_root / "samples").rglob("*"):
        if f.is_file():
            target = out / f.relative_to(real_root)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(f)
    (out / "maps").mkdir(exist_ok=True)
    shutil.copy(real_root / "maps" / "placeholder.png", out / "maps" / "placeholder.png")
    return out


def _boxes(scenes: list[dict], samples: list[dict], categories: list[dict], n_samples: int,
           per_scene: int) -> tuple[list[dict], list[dict]]:
    """Instances and their annotation rows, linked prev/next along each scene's samples."""
    cars = [c["token"] for c in categories if c["name"].startswith("vehicle.")] or [categories[0]["token"]]
    instances, rows = [], []
    for si, scene in enumerate(scenes):
        tokens = [s["token"] for s in samples[si * n_samples:(si + 1) * n_samples]]
        for b in range(per_scene):
            inst = _tok("instance", scene["name"], b)
            ann = [_tok("ann", inst, k) for k in range(n_samples)]
            instances.append({"token": inst, "category_token": cars[b % len(cars)], "nbr_annotations": n_samples,
                              "first_annotation_token": ann[0], "last_annotation_token": ann[-1]})
            for k, tok in enumerate(tokens):
                rows.append({
                    "token": ann[k], "sample_token": tok, "instance_token": inst, "visibility_token": "4",
                    "attribute_tokens": [], "translation": [600.0 + 4.0 * (b % 20) + k, 1600.0 + 5.0 * (b // 20)
                                                            + 100.0 * si, 1.0],
                    "size": [1.9, 4.6, 1.6], "rotation": [1.0, 0.0, 0.0, 0.0],
                    "prev": ann[k - 1] if k else "", "next": ann[k + 1] if k + 1 < n_samples else "",
                    "num_lidar_pts": 10, "num_radar_pts": 0,
                })
    return instances, rows
