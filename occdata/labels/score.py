"""File IO around `occdata.labels.fidelity`: score a folder of generated labels against a folder of
true ones for a nuScenes-format tree (both in Occ3D's layout)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occdata.formats.gridfiles import read_grid_label
from occdata.formats.gridspec import GRID_PRESETS, GridSpec, LabelFrame, LabelLayout
from occdata.formats.occ3d import label_path, read_label
from occdata.geometry import invert_rigid
from occdata.labels.boxes import box_class
from occdata.labels.fidelity import Fidelity, score_scene
from occdata.nuscenes import load_nuscenes
from occdata.nuscenes.annotations import load_annotations

__all__ = ["TreeScore", "score_tree"]


@dataclass(frozen=True)
class TreeScore:
    """Voxel counts over every keyframe, and the moving instances' (inside, total) voxels pooled."""

    voxels: Fidelity
    moving_inside: int
    moving_total: int
    worst_instance: float  # lowest per-instance share (instances with >= 20 voxels)
    bands: tuple[Fidelity, ...] = ()  # per band of `occdata.labels.fidelity.BANDS`

    @property
    def moving_fraction(self) -> float:
        return self.moving_inside / max(self.moving_total, 1)


def _arrays(folder: Path, scene: str, token: str, *keys: str, spec: GridSpec = GRID_PRESETS["occ3d"]
            ) -> tuple[np.ndarray, ...]:
    path = label_path(folder, scene, token)
    label = read_label(path) if spec.name == "occ3d" else read_grid_label(spec, path)
    return tuple(label[k] if k in label else np.zeros(spec.shape, np.uint8) for k in keys)


def score_tree(root: Path, generated: Path, truth: Path, spec: GridSpec = GRID_PRESETS["occ3d"]) -> TreeScore:
    """Score `generated/<scene>/<token>/labels.npz` against `truth/...` for every keyframe of `root`,
    both on `spec`: Occ3D's grid, or an Occ3D-style custom one (key ego, Occ3D's layout and classes:
    `occdata labels|synth --voxel-size/--range`'s `occ3d-<V>m/` folders)."""
    if spec.frame is not LabelFrame.KEY_EGO or spec.layout is not LabelLayout.OCC3D:
        raise ValueError(f"score_tree scores key-ego grids in Occ3D's layout, not {spec.name}")
    grid = spec.grid
    ds = load_nuscenes(root, None)
    ann = load_annotations(root, ds.version)
    class_of = {b.instance_token: box_class(b) for bs in ann.boxes_by_sample.values() for b in bs}
    voxels, inside, total, worst = Fidelity(), 0, 0, 1.0
    bands: list[Fidelity] = []
    for sc in ds.scenes:
        toks = sc.sample_tokens
        gens = [_arrays(generated, sc.name, t, "semantics", spec=spec)[0] for t in toks]
        truths = [_arrays(truth, sc.name, t, "semantics", "mask_lidar", "mask_camera", spec=spec) for t in toks]
        Ts = [invert_rigid(ds.sample(t).T_global_from_keyego) for t in toks]
        score = score_scene(gens, truths, Ts, [list(ann.boxes_by_sample.get(t, ())) for t in toks], class_of,
                            grid)
        voxels.add(score.voxels)
        bands = bands or [Fidelity() for _ in score.bands]
        for band, more in zip(bands, score.bands, strict=True):
            band.add(more)
        inside += sum(v[0] for v in score.moving.values())
        total += sum(v[1] for v in score.moving.values())
        worst = min(worst, score.worst_instance())
    return TreeScore(voxels, inside, total, worst, tuple(bands))
