"""Open-road smear and hit recall of `occdata labels` on the real Lyft keyframes (no boxes), naive vs carved.

A self-consistency check: each keyframe's labels are held against that keyframe's own LiDAR returns
(all of its LiDARs), with no rule of the carving in it. On Occ3D's grid (key ego, 0.4 m voxels), per
keyframe k:

- a column's **ground** is `ground_ref`: the lowest of k's returns in the columns within
  `GROUND_REACH_M` (the 10th percentile of their lowest returns: a car roof has road beside it);
- an **open-road column** is one where k has a return within `GROUND_BAND_M` of that ground and none
  from there up to `BAND_TOP_M` above it: k saw the road and nothing standing on it;
- the **open-road band** is the voxels of those columns whose centre lies `BAND_BOTTOM_M`-`BAND_TOP_M`
  over the ground (vehicle heights) and that k's own rays passed through (each ray cut 0.4 m short of
  its return): space k saw empty at its own time;
- **smear** is the occupied voxels of k's labels in its open-road band; the share of naive accumulation's
  smear that a run removes is `1 - smear(run) / smear(naive)`, summed over keyframes;
- **hit recall** is the share of k's own returns (off the ego car, in the grid) whose voxel is occupied
  in k's labels.

    python -m benchmarks.labels_lyft_smear --json docs/results/labels_lyft_smear.json
    python -m benchmarks.labels_lyft_smear --carve-options '{"near": 0}' --json out.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import SHARED_DATA, write_json
from benchmarks.provenance import machine
from occdata.constants import EGO_BOX, FREE_LABEL, GRID
from occdata.geometry import invert_rigid, transform_points
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.labels.carve import CarveOptions
from occdata.nuscenes import load_lidar_points, load_nuscenes
from occdata.nuscenes.records import SampleRecord
from occdata.visibility.masks import lidar_ray_mask

__all__ = ["KeyframeReturns", "hit_recall", "keyframe_returns", "open_road_band", "smear_figures"]

GROUND_REACH_M = 2.0  # columns within this (in x and y) give a column's ground
GROUND_BAND_M = 0.3  # a return this close to the ground is on it
BAND_BOTTOM_M, BAND_TOP_M = 0.5, 3.0  # vehicle heights over the ground
RAY_CUT_M = 0.4  # rays stop this short of their return: its own surface is not seen empty


@dataclass(frozen=True)
class KeyframeReturns:
    """A keyframe's own LiDAR returns in its key ego (= Occ3D's grid frame): `points (N, 3) float64`
    off the ego car, and the origin of the LiDAR of each, `origins (N, 3) float64`."""

    points: np.ndarray
    origins: np.ndarray


def keyframe_returns(sample: SampleRecord) -> KeyframeReturns:
    """Every LiDAR of `sample` at its keyframe, in key ego, the ego car's own returns left out."""
    T_key_from_global = invert_rigid(sample.T_global_from_keyego)
    pts, orgs = [], []
    lo, hi = np.array(EGO_BOX[0]), np.array(EGO_BOX[1])
    for rec in sample.lidars:
        raw = load_lidar_points(rec.path)[:, :3].astype(np.float64)
        points_ego = transform_points(rec.T_ego_from_lidar, raw)
        off_ego = ~((points_ego >= lo) & (points_ego <= hi)).all(axis=1)
        T_key_from_lidar = T_key_from_global @ rec.T_global_from_ego @ rec.T_ego_from_lidar
        p = transform_points(T_key_from_lidar, raw[off_ego])
        pts.append(p)
        orgs.append(np.broadcast_to(T_key_from_lidar[:3, 3], p.shape))
    return KeyframeReturns(np.concatenate(pts), np.ascontiguousarray(np.concatenate(orgs)))


def _in_grid(idx: np.ndarray) -> np.ndarray:
    return ((idx >= 0) & (idx < np.array(GRID.shape))).all(axis=1)


def _column_ground(points: np.ndarray) -> np.ndarray:
    """`(X, Y) float64`: each column's ground height (module docstring; NaN with no return in reach)."""
    X, Y, _ = GRID.shape
    ij = np.floor((points[:, :2] - np.asarray(GRID.lower[:2])) / GRID.voxel_size).astype(np.int64)
    ok = (ij >= 0).all(axis=1) & (ij[:, 0] < X) & (ij[:, 1] < Y)
    lowest = np.full((X, Y), np.inf)
    np.minimum.at(lowest, (ij[ok, 0], ij[ok, 1]), points[ok, 2])
    r = int(round(GROUND_REACH_M / GRID.voxel_size))
    padded = np.pad(np.where(np.isfinite(lowest), lowest, np.nan), r, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (2 * r + 1, 2 * r + 1))
    seen = np.isfinite(windows).any(axis=(2, 3))
    ground = np.full((X, Y), np.nan)
    ground[seen] = np.nanpercentile(windows[seen], 10, axis=(1, 2))
    return ground


def open_road_band(ret: KeyframeReturns) -> tuple[np.ndarray, np.ndarray]:
    """The keyframe's open-road band (module docstring) on Occ3D's grid, `(X, Y, Z) bool`, and each
    voxel centre's height over its column's ground, `(X, Y, Z) float64` (m; NaN: no ground in reach)."""
    ground = _column_ground(ret.points)
    X, Y, Z = GRID.shape
    idx = GRID.index_of(ret.points)
    ok = ((idx[:, :2] >= 0) & (idx[:, :2] < np.array([X, Y]))).all(axis=1)
    i, j, z = idx[ok, 0], idx[ok, 1], ret.points[ok, 2]
    over = z - ground[i, j]
    on_ground = np.zeros((X, Y), bool)
    on_ground[i[np.abs(over) <= GROUND_BAND_M], j[np.abs(over) <= GROUND_BAND_M]] = True
    standing = np.zeros((X, Y), bool)
    tall = (over > GROUND_BAND_M) & (over <= BAND_TOP_M)
    standing[i[tall], j[tall]] = True
    open_road = on_ground & ~standing
    centres_z = GRID.lower[2] + GRID.voxel_size * (np.arange(Z) + 0.5)
    height = centres_z[None, None, :] - ground[:, :, None]
    band = open_road[:, :, None] & (height >= BAND_BOTTOM_M) & (height <= BAND_TOP_M)
    return band & _seen_empty(ret), height


def _seen_empty(ret: KeyframeReturns) -> np.ndarray:
    """`(X, Y, Z) bool`: voxels the keyframe's rays passed through (cut `RAY_CUT_M` short) holding none
    of its returns."""
    d = ret.points - ret.origins
    length = np.linalg.norm(d, axis=1, keepdims=True)
    short = ret.origins + d * np.clip(1 - RAY_CUT_M / np.maximum(length, 1e-9), 0, 1)
    shape = np.asarray(GRID.shape, np.int64)
    crossed = lidar_ray_mask(ret.origins, np.ascontiguousarray(short), np.asarray(GRID.lower, np.float64),
                             GRID.voxel_size, shape).astype(bool)
    idx = GRID.index_of(ret.points)
    crossed[tuple(idx[_in_grid(idx)].T)] = False
    return crossed


def hit_recall(ret: KeyframeReturns, semantics: np.ndarray) -> tuple[int, int]:
    """`(returns in the grid whose voxel is occupied in semantics (X, Y, Z) uint8, returns in the grid)`."""
    idx = GRID.index_of(ret.points)
    idx = idx[_in_grid(idx)]
    return int((semantics[tuple(idx.T)] != FREE_LABEL).sum()), len(idx)


def _labels(out: Path, sample: SampleRecord) -> np.ndarray:
    with np.load(out / sample.scene_name / sample.token / "labels.npz", allow_pickle=False) as z:
        return z["semantics"]


def smear_figures(samples: list[SampleRecord], runs: dict[str, Path]) -> dict[str, dict[str, Any]]:
    """Per run (name -> its output tree): smear per keyframe and in all, hit recall; each keyframe's
    returns and band are computed once."""
    rows: dict[str, dict[str, Any]] = {n: {"smear": [], "hits": 0, "returns": 0} for n in runs}
    band_sizes = []
    for s in samples:
        ret = keyframe_returns(s)
        band, height = open_road_band(ret)
        band_sizes.append(int(band.sum()))
        for name, out in runs.items():
            smear = band & (_labels(out, s) != FREE_LABEL)
            rows[name]["smear"].append(int(smear.sum()))
            by_height = rows[name].setdefault("smear_by_height_m", {})
            for lo in np.arange(BAND_BOTTOM_M, BAND_TOP_M, 0.5):
                key = f"{lo:.1f}-{lo + 0.5:.1f}"
                by_height[key] = by_height.get(key, 0) + int((smear & (height >= lo) & (height < lo + 0.5)).sum())
            sem = _labels(out, s)
            h, n = hit_recall(ret, sem)
            rows[name]["hits"] += h
            rows[name]["returns"] += n
    for row in rows.values():
        row["smear_total"] = int(sum(row["smear"]))
        row["hit_recall"] = row["hits"] / max(row["returns"], 1)
        row["band_voxels"] = band_sizes
    return rows


def _label(root: Path, out: Path, opts: LabelOptions) -> float:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.process_time()
    generate_labels(LabelsConfig(root=root, out=out, options=opts, progress=False))
    return time.process_time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=SHARED_DATA / "lyft-real")
    ap.add_argument("--carve-options", nargs="*", default=[], metavar="JSON",
                    help='also carve with these CarveOptions, e.g. \'{"near": 0}\'')
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    work = a.keep or Path(tempfile.mkdtemp(prefix="labels_lyft_smear_"))
    work.mkdir(parents=True, exist_ok=True)
    variants = {"naive": LabelOptions(carve=False), "carve": LabelOptions()}  # no boxes here: carved by default
    for spec in a.carve_options:
        variants[f"carve {spec}"] = LabelOptions(carve_options=CarveOptions(**json.loads(spec)))
    runs, cpu = {}, {}
    for n, (name, opts) in enumerate(variants.items()):
        runs[name] = work / f"gen_{n}"
        cpu[name] = _label(a.root, runs[name], opts)
    samples = load_nuscenes(a.root, None).samples
    rows = smear_figures(samples, runs)
    naive = max(rows["naive"]["smear_total"], 1)
    for name, row in rows.items():
        row["smear_removed_vs_naive"] = 1.0 - row["smear_total"] / naive
        row["hit_recall_loss_vs_naive"] = rows["naive"]["hit_recall"] - row["hit_recall"]
        row["cpu_seconds_labels"] = cpu[name]
        print(name, json.dumps({k: row[k] for k in ("smear_total", "smear_removed_vs_naive", "hit_recall",
                                                   "cpu_seconds_labels")}), flush=True)
    if a.json:
        write_json({"machine": machine(), "root": str(a.root), "rows": rows}, a.json, indent=1)


if __name__ == "__main__":
    main()
