"""`occdata labels` on the real scene-0916 (keyframes, boxes, no lidarseg, no sweep files): the
moving-object figure (ours vs the global-aggregation control) and pictures of the generated labels.

    python -m benchmarks.labels_real [--root ../shared/data/nuscenes-real-seq] [--pictures docs/img] [--json out.json]

The real data stays outside the repository: labels go to a temporary folder; only the pictures
(renderings of the generated labels, without the camera images) and the figures are written.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import SHARED_DATA, write_json
from benchmarks.provenance import REPO, machine
from occdata.geometry import invert_rigid
from occdata.labels.boxes import box_class
from occdata.labels.fidelity import moving_containment
from occdata.nuscenes import load_nuscenes
from occdata.nuscenes.annotations import load_annotations
from occdata.view.render import prediction_picture

__all__: list[str] = []


def _generate(root: Path, out: Path, extra: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(root), "--out", str(out),
                    "--no-progress", *extra], check=True, cwd=REPO)
    return time.perf_counter() - t0


def _load(out: Path, scene: str, tok: str) -> dict[str, np.ndarray]:
    with np.load(out / scene / tok / "labels.npz", allow_pickle=False) as z:
        return {k: z[k].copy() for k in z.files}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=SHARED_DATA / "nuscenes-real-seq")
    ap.add_argument("--pictures", type=Path, default=None, help="folder for labels_real_kNN.png")
    ap.add_argument("--keyframes", default="0,20,40", help="keyframe indices to draw")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    ds = load_nuscenes(a.root, None)
    ann = load_annotations(a.root, ds.version)
    class_of = {b.instance_token: box_class(b) for bs in ann.boxes_by_sample.values() for b in bs}
    work = Path(tempfile.mkdtemp(prefix="labels_real_"))
    result: dict[str, object] = {"machine": machine(), "root": str(a.root)}
    for name, extra in {"ours": [], "control": ["--no-boxes"]}.items():
        seconds = _generate(a.root, work / name, extra)
        for sc in ds.scenes:
            gens = [_load(work / name, sc.name, t)["semantics"] for t in sc.sample_tokens]
            Ts = [invert_rigid(ds.sample(t).T_global_from_keyego) for t in sc.sample_tokens]
            boxes = [list(ann.boxes_by_sample.get(t, ())) for t in sc.sample_tokens]
            moving = moving_containment(gens, Ts, boxes, class_of)
            inside = sum(v[0] for v in moving.values()) / max(sum(v[1] for v in moving.values()), 1)
            per = sorted(v[0] / v[1] for v in moving.values() if v[1] >= 20)
            result[name] = {"seconds": seconds, "keyframes": len(gens), "moving_instances": len(moving),
                            "moving_inside": inside, "moving_inside_worst": per[0] if per else None,
                            "moving_voxels": sum(v[1] for v in moving.values())}
            print(name, json.dumps(result[name]), flush=True)
    if a.pictures:
        a.pictures.mkdir(parents=True, exist_ok=True)
        sc = ds.scenes[0]
        for k in (int(x) for x in a.keyframes.split(",")):
            s = ds.sample(sc.sample_tokens[k])
            ours = _load(work / "ours", sc.name, s.token)
            control = _load(work / "control", sc.name, s.token)
            # No camera images: the pictures go into the repository, the real data must not.
            pic = prediction_picture([], ours["semantics"], control["semantics"], ours["mask_camera"], width=1200,
                                     title=f"{sc.name} keyframe {k}; black = static, class unknown (no lidarseg)",
                                     names=("occdata labels (boxes)", "control: global aggregation"))
            path = a.pictures / f"labels_real_k{k:02d}.png"
            cv2.imwrite(str(path), pic[:, :, ::-1])
            print("wrote", path)
    if a.json:
        write_json(result, a.json, indent=1)


if __name__ == "__main__":
    main()
