"""A plain summary of a nuScenes-format tree (what `occdata scan` prints)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

from occdata.errors import OccDataError
from occdata.nuscenes.annotations import load_annotations
from occdata.nuscenes.reader import load_nuscenes, validate_sample
from occdata.nuscenes.records import NuScenesDataset
from occdata.nuscenes.rig import RigChoice
from occdata.nuscenes.splits import SplitChoice

__all__ = ["scan_tree"]


def scan_tree(root: Path, version: str | None, check_files: bool, rig: RigChoice | None = None,
              splits: SplitChoice | None = None) -> dict[str, Any]:
    """Read the tree and summarise it. Raises `OccDataError` on any broken reference (the boxes' too:
    `load_annotations`, as `occdata labels` reads them) and on any
    sample that `occdata build` would reject from its tables alone (unusable values, paths outside
    the root, NaN or non-rigid calibration and poses, invalid intrinsics; missing files with
    `check_files`): one line naming the first such sample and how many there are.

    `sweeps`: the non-keyframe LIDAR_TOP sweeps between consecutive keyframes (min / mean / max
    over keyframes that have a previous keyframe), the total, and with `check_files` how many of
    their files exist (none in a keyframe-only download: not an error). `rig`: the cameras and
    LiDARs read (`rig` in the summary; `left_out` names every sensor that is not); `splits`: where
    each scene's split comes from."""
    ds = load_nuscenes(root, version, check_files=check_files, sweeps=True, rig=rig, splits=splits)
    boxes = load_annotations(ds.root, ds.version)  # checked as `occdata labels` reads them (none: a test split)
    bad: list[str] = []
    for s in ds.samples:
        try:
            validate_sample(s)
        except OccDataError as exc:
            bad.append(str(exc))
    if bad:
        more = f" (and {len(bad) - 1} more sample(s) with problems)" if len(bad) > 1 else ""
        raise OccDataError(bad[0] + more)
    per_split: Counter[str] = Counter()
    for sc in ds.scenes:
        per_split[sc.split] += len(sc.sample_tokens)
    return {
        "root": str(ds.root),
        "version": ds.version,
        "scenes": len(ds.scenes),
        "samples": len(ds.samples),
        "samples_per_split": dict(sorted(per_split.items())),
        "scenes_per_split": dict(sorted(Counter(sc.split for sc in ds.scenes).items())),
        "rig": ds.rig.as_attr(),
        "left_out": list(ds.rig.left_out),
        "boxes": sum(len(b) for b in boxes.boxes_by_sample.values()),
        "files_checked": check_files,
        "sweeps": _sweep_summary(ds, check_files),
        "warnings": list(ds.warnings),
    }


def _sweep_summary(ds: NuScenesDataset, check_files: bool) -> dict[str, Any]:
    between = [len(s.sweeps) for s in ds.samples if s.index_in_scene > 0]
    out: dict[str, Any] = {
        "total": sum(len(s.sweeps) for s in ds.samples),
        "per_keyframe_min": min(between, default=0),
        "per_keyframe_mean": round(sum(between) / len(between), 3) if between else 0.0,
        "per_keyframe_max": max(between, default=0),
    }
    if check_files:
        out["files_present"] = sum(sw.path.is_file() for s in ds.samples for sw in s.sweeps)
    return out
