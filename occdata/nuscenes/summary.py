"""A plain summary of a nuScenes-format tree (what `occdata scan` prints)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

from occdata.nuscenes.reader import load_nuscenes

__all__ = ["scan_tree"]


def scan_tree(root: Path, version: str | None, check_files: bool) -> dict[str, Any]:
    """Read the tree (raising `OccDataError` on any broken reference) and summarise it."""
    ds = load_nuscenes(root, version, check_files=check_files)
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
        "files_checked": check_files,
    }
