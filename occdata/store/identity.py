"""A store's build identity: what a resumed build must match, and how to say what differs."""

from __future__ import annotations

import zlib
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occdata.nuscenes.splits import SplitChoice
from occdata.store.labelgrid import is_default_grid

if TYPE_CHECKING:
    from occdata.nuscenes import NuScenesDataset
    from occdata.store.config import BuildConfig

__all__ = ["build_identity", "identity_diff"]

# build_identity key -> what the user changes to change it
_IDENTITY_OPTION = {
    "source_root": "--root", "source_version": "--version", "gts": "--gts", "splits": "--split",
    "block_samples": "--block-samples", "options.image_scale": "--image-scale",
    "options.jpeg_quality": "--jpeg-quality", "options.min_depth": "min_depth",
    "options.lidar_sweeps": "--lidar-sweeps", "labels_format": "the format of the --gts files",
    "label_grid": "--gts-grid / --voxel-size / --range", "rig.cameras": "--cameras", "rig.lidars": "--lidars",
    "rig.reference_lidar": "--reference-lidar", "scene_splits.file": "--split-file",
    "scene_splits.unlisted": "--unlisted-split",
    "sample_tokens_crc32": "the sample list in the tables",
}


def build_identity(config: BuildConfig, ds: NuScenesDataset, gts: Path | None,
                   label_format: str = "occ3d") -> dict[str, Any]:
    """What a resumed build must match (workers, resume and on_error may change between runs);
    `gts`: the labels folder the build reads (`config.labels().folder`); `label_format` its files'
    format, recorded only when not "occ3d" (identities from before flow stay as they were); the
    labels' grid, recorded only when not Occ3D's (`config.grid`); the rig, only when not nuScenes'."""
    extra: dict[str, Any] = {} if label_format == "occ3d" else {"labels_format": label_format}
    if not ds.rig.is_nuscenes:
        extra["rig"] = ds.rig.as_attr()
    if config.scene_splits != SplitChoice():  # the default split rule leaves the identity as it was
        extra["scene_splits"] = config.scene_splits.describe()
    if not is_default_grid(config.grid):
        g = config.grid.describe()  # type: ignore[union-attr]
        extra["label_grid"] = {k: g[k] for k in ("name", "voxel_size", "lower", "upper", "frame", "layout")}
    return {
        "source_root": str(ds.root),
        "source_version": ds.version,
        "gts": str(Path(gts).resolve()) if gts else None,
        "splits": list(config.splits),
        "block_samples": config.block_samples,
        "options": asdict(config.options),
        "sample_tokens_crc32": _tokens_crc32(ds.sample_tokens()),
    } | extra


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def identity_diff(stored: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """One phrase per differing input/option: `--image-scale: store 1.0, now 0.5`."""
    a, b = _flatten(stored), _flatten(now)
    out = []
    for key in sorted(set(a) | set(b), key=lambda k: list(_IDENTITY_OPTION).index(k) if k in _IDENTITY_OPTION else 99):
        if a.get(key, "<unset>") != b.get(key, "<unset>"):
            if key == "sample_tokens_crc32":
                out.append("the sample list in the tables differs (tables edited?)")
            else:
                was, now_ = a.get(key, "<unset>"), b.get(key, "<unset>")
                out.append(f"{_IDENTITY_OPTION.get(key, key)}: store {was!r}, now {now_!r}")
    return out


def _tokens_crc32(tokens: list[str]) -> int:
    """crc32 of the tokens joined, computed a token at a time (the joined text grew with the dataset)."""
    crc = 0
    for tok in tokens:
        crc = zlib.crc32(tok.encode(), crc)
    return crc
