"""One picture per label grid preset on the real scene-0916 (docs/labels.md "Grids").

    python -m benchmarks.labels_presets [--root ../shared/data/nuscenes-real-seq] [--keyframe 20] \
        [--pictures docs/img] [--json docs/results/labels_presets.json]

Runs `occdata labels` once with all four presets (`--grid occ3d --grid openocc-v2 --grid surroundocc
--grid openoccupancy`, one aggregation) into a temporary folder (the real data stays outside the
repository), reads keyframe `--keyframe` of each grid back the way its benchmark's loader does
(`occdata.formats.gridfiles.read_grid_label`), maps its ids back to our classes for the colours, and draws
each grid as it lies in its own frame: a 3D view and a top view (x up, y left, as the grid's axes;
the LiDAR-frame grids therefore appear turned: LIDAR_TOP's x points to the car's right). Writes
`labels_presets_kNN.png` and, with `--json`, the occupied-voxel counts per grid and class.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import SHARED_DATA, write_json
from benchmarks.provenance import REPO, machine
from occdata.constants import CLASS_NAMES, FREE_LABEL
from occdata.formats.gridfiles import LabelSite, grid_label_path, read_grid_label, to_occ3d_ids
from occdata.formats.gridspec import GRID_PRESETS, GridSpec, LabelFrame
from occdata.nuscenes import load_nuscenes
from occdata.view.render import View, bev_top_view, class_legend, render_voxels

__all__: list[str] = []

_PANEL_W = 400


def panel(spec: GridSpec, labels: np.ndarray) -> np.ndarray:
    """A 3D view over a top view of one grid's labels (our class ids), titled, `_PANEL_W` wide."""
    key_ego = spec.frame is LabelFrame.KEY_EGO
    view3d = render_voxels(labels, size=(300, _PANEL_W), view=View(), grid=spec.grid, ego=key_ego)
    X = spec.shape[0]
    top = bev_top_view(labels, cell_px=max(1, round(_PANEL_W / X)),
                       voxel_size=spec.grid.voxel_size if key_ego else None)
    top = cv2.resize(top, (_PANEL_W, _PANEL_W), interpolation=cv2.INTER_NEAREST)
    g = spec.grid
    head = np.full((44, _PANEL_W, 3), 255, np.uint8)
    lines = (f"{spec.name}: {g.voxel_size:g} m, {'x'.join(map(str, spec.shape))}",
             f"{'key ego' if key_ego else 'LIDAR_TOP'} frame, z {g.lower[2]:g}..{g.upper[2]:g} m")
    for k, text in enumerate(lines):
        cv2.putText(head, text, (6, 17 + 20 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    body = np.vstack([head, view3d, top])
    body[:, -1] = 200  # a thin separator between panels
    return body


def _site(root: Path, keyframe: int) -> LabelSite:
    ds = load_nuscenes(root, None)
    samples = sorted(ds.samples, key=lambda s: s.timestamp)
    if not 0 <= keyframe < len(samples):
        raise SystemExit(f"--keyframe {keyframe}: the tree has {len(samples)} keyframes")
    s = samples[keyframe]
    return LabelSite(s.scene_name, s.scene_token, s.token, s.lidar.token, s.lidar.path.name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=SHARED_DATA / "nuscenes-real-seq")
    ap.add_argument("--keyframe", type=int, default=20)
    ap.add_argument("--pictures", type=Path, default=Path("docs/img"))
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    site = _site(a.root, a.keyframe)
    out = Path(tempfile.mkdtemp(prefix="labels_presets_"))
    grids = [x for name in GRID_PRESETS for x in ("--grid", name)]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(a.root), "--out", str(out),
                    "--no-progress", *grids], check=True, cwd=REPO)
    seconds = time.perf_counter() - t0
    panels, present, counts = [], set(), {}
    for spec in GRID_PRESETS.values():
        grid_root = out if spec.name == "occ3d" else out / spec.name
        labels = to_occ3d_ids(spec, read_grid_label(spec, grid_label_path(spec, grid_root, site))["semantics"])
        panels.append(panel(spec, labels))
        classes, n = np.unique(labels[labels != FREE_LABEL], return_counts=True)
        present |= set(classes.tolist())
        counts[spec.name] = {CLASS_NAMES[c]: int(k) for c, k in zip(classes, n, strict=True)}
    picture = np.hstack(panels)
    picture = np.vstack([picture, class_legend(sorted(present), picture.shape[1])])
    a.pictures.mkdir(parents=True, exist_ok=True)
    path = a.pictures / f"labels_presets_k{a.keyframe:02d}.png"
    cv2.imwrite(str(path), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    print(f"wrote {path} ({seconds:.0f} s for the labels of 4 grids)")
    if a.json:
        write_json({"machine": machine(), "root": str(a.root), "keyframe": a.keyframe,
                    "sample_token": site.sample_token, "labels_wall_s": seconds, "occupied_voxels": counts,
                    "command": "python -m benchmarks.labels_presets " + " ".join(sys.argv[1:])}, a.json)


if __name__ == "__main__":
    main()
