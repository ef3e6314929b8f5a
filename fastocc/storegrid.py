"""The checks that a store fits a model, each one line at the start of a command instead of an error deep
in the loss, the metric or the loader:

- `check_store_grid`: the store's label grid is the model's output grid (`fastocc train`, `eval`,
  `predict`; a store built with `occdata build --gts-grid ...` is not);
- `check_store_rig` / `check_rig_cameras`: the store's (or a deployment rig's) cameras are the ones a
  checkpoint was trained on, in the same order (train `--resume`, `eval`, `predict`, `export`, `Predictor`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from fastocc.model.config import ModelConfig
from occdata.errors import OccDataError
from occdata.formats.gridspec import LabelFrame
from occdata.store.layout import store_rig
from occdata.store.reader import StoreReader, open_store

__all__ = ["check_rig_cameras", "check_store_grid", "check_store_rig"]


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


def _cams(cameras: Sequence[str]) -> str:
    return f"{len(cameras)} cameras {','.join(cameras)}"


def check_rig_cameras(trained: Sequence[str] | None, num_cams: int, cameras: Sequence[str], model: str, data: str,
                      command: str) -> None:
    """Raise one `OccDataError` line naming both rigs unless `cameras` (the data's, in its order) are the
    ones `model` was trained on: `trained` (its camera order; None when unknown: then only the count
    `num_cams` is checked). `data` names where `cameras` come from, `command` what cannot run."""
    cameras = tuple(cameras)
    same = tuple(trained) == cameras if trained is not None else num_cams == len(cameras)
    if same:
        return
    was = _cams(tuple(trained)) if trained is not None else f"{num_cams} cameras"
    raise OccDataError(
        f"{model} was trained on a rig of {was}; {data} holds {_cams(cameras)}, so fastocc {command} cannot "
        f"use it: give data of the checkpoint's rig (occdata build --cameras picks and orders cameras) or "
        f"train on this one")


def check_store_rig(store: str | Path | StoreReader, trained: Sequence[str] | None, num_cams: int, model: str,
                    command: str) -> None:
    """`check_rig_cameras` with a store's cameras (its rig attribute, or its `camera_order`)."""
    reader = store if isinstance(store, StoreReader) else open_store(store)
    check_rig_cameras(trained, num_cams, store_rig(reader.attrs)["cameras"], model, f"store {reader.path}", command)
