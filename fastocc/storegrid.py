"""The one check that a store's label grid is the model's output grid, for `fastocc train`, `eval` and
`predict`: a store built on another grid (`occdata build --gts-grid ...`) stops the command at start in one
line, instead of a shape error deep in the loss, the metric or the loader."""

from __future__ import annotations

from pathlib import Path

from fastocc.model.config import ModelConfig
from occdata.errors import OccDataError
from occdata.formats.gridspec import LabelFrame
from occdata.store.reader import StoreReader, open_store

__all__ = ["check_store_grid"]


def check_store_grid(store: str | Path | StoreReader, model_cfg: ModelConfig, command: str = "train") -> None:
    """Raise one `OccDataError` line unless the store's labels are on `model_cfg.fine_grid` (shape, voxel
    size, lower corner) in the key ego frame; `command` names what cannot run."""
    reader = store if isinstance(store, StoreReader) else open_store(store)
    g, want = reader.grid, model_cfg.fine_grid
    got = g.grid
    if (got.shape, got.voxel_size, tuple(got.lower), g.frame) == (
            want.shape, want.voxel_size, tuple(want.lower), LabelFrame.KEY_EGO):
        return
    frame = "key ego" if g.frame is LabelFrame.KEY_EGO else "LIDAR_TOP"
    raise OccDataError(
        f"{reader.path}: its labels are on a grid of shape {got.shape}, {got.voxel_size:g} m voxels from "
        f"{tuple(got.lower)} in the {frame} frame (grid {g.name}); this model predicts {want.shape} voxels of "
        f"{want.voxel_size:g} m from {tuple(want.lower)} in key ego (Occ3D's grid), so fastocc {command} "
        "cannot use it: build the store from labels on that grid (occdata labels --grid occ3d)")
