"""One sample turned into what is drawn: voxel groups (label, prediction, error view) with their layers and
places, the ego box, and the notes that say in words what is missing. No viser, no torch."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occdata.constants import EGO_BOX, GRID
from occdata.view.config import FrameOptions
from occdata.view.source import SampleData
from occdata.view.voxels import VoxelLayer, error_ids, label_ids, layers_from_ids, speed_ids

__all__ = ["SIDE_OFFSET_M", "Frame", "VoxelGroup", "compose_frame", "ego_box_center"]

SIDE_OFFSET_M = 44.0  # label | prediction: each grid moved this far along y (grids are 80 m wide)
_GROUND_CLASSES = (11, 12, 13, 14)  # driveable_surface, other_flat, sidewalk, terrain


@dataclass(frozen=True, eq=False)
class VoxelGroup:
    """A grid drawn at `offset` (m, added to key-ego positions): `name` (truth, pred or error),
    `title` for people, its `layers`."""

    name: str
    title: str
    offset: tuple[float, float, float]
    layers: tuple[VoxelLayer, ...]


@dataclass(frozen=True, eq=False)
class Frame:
    """Everything drawn for one sample: the groups, where the sensors go (`sensor_offset`), the ego box
    centre (key ego) and `notes`: sentences about what cannot be shown (no labels, no prediction, ...)."""

    groups: tuple[VoxelGroup, ...]
    sensor_offset: tuple[float, float, float]
    ego_center: tuple[float, float, float]
    notes: tuple[str, ...]


def ego_box_center(semantics: np.ndarray | None) -> tuple[float, float, float]:
    """Centre of the ego box (`EGO_BOX`, key ego, m), its z measured from the highest ground voxel
    within 4 m of the origin (z = 0 m ground when there is none)."""
    ground_top = 0.0
    if semantics is not None:
        lab = np.asarray(semantics)
        n = int(round(4.0 / GRID.voxel_size))
        cx, cy = GRID.shape[0] // 2, GRID.shape[1] // 2
        patch = lab[cx - n:cx + n, cy - n:cy + n]
        k = np.flatnonzero(np.isin(patch, _GROUND_CLASSES).any(axis=(0, 1)))
        if k.size:
            ground_top = GRID.lower[2] + GRID.voxel_size * (int(k.max()) + 1)
    (lx, ly, lz), (hx, hy, hz) = EGO_BOX
    return (lx + hx) / 2, (ly + hy) / 2, ground_top + (lz + hz) / 2


def _keep(layers: list[VoxelLayer], opts: FrameOptions) -> tuple[VoxelLayer, ...]:
    return tuple(layer for layer in layers if opts.outside_mask or not layer.ghost)


def compose_frame(sample: SampleData, opts: FrameOptions) -> Frame:
    """The groups, notes and places for `sample` drawn with `opts`."""
    notes: list[str] = []
    mask = None
    if opts.mask != "none":
        mask = sample.masks.get(opts.mask)
        if mask is None:
            notes.append(f"This sample has no '{opts.mask}' mask: all voxels are drawn.")
    truth, pred = sample.semantics, sample.pred
    if truth is None:
        notes.append("No labels for this sample (a test split, or a store built without labels): "
                     "only the cameras, LiDAR points and prediction can be shown.")
    if pred is None and opts.view not in ("label", "speed"):
        notes.append("No prediction for this sample in the prediction folder.")
    if opts.view == "speed" and truth is not None and sample.flow is None:
        notes.append("No flow in this store (it comes from OpenOcc v2 labels, docs/store.md): the speed view "
                     "has nothing to colour.")
    groups: list[VoxelGroup] = []
    wants = {"label": ("truth",), "prediction": ("pred",), "side": ("truth", "pred"), "error": ("error",),
             "speed": ("speed",)}
    side = opts.view == "side"
    for name in wants[opts.view]:
        offset = (0.0, (SIDE_OFFSET_M if name == "truth" else -SIDE_OFFSET_M) if side else 0.0, 0.0)
        if name == "truth" and truth is not None:
            layers = layers_from_ids(label_ids(truth, mask))
            groups.append(VoxelGroup("truth", "label", offset, _keep(layers, opts)))
        elif name == "pred" and pred is not None:
            layers = layers_from_ids(label_ids(pred, mask))
            groups.append(VoxelGroup("pred", "prediction", offset, _keep(layers, opts)))
        elif name == "speed" and truth is not None and sample.flow is not None:
            layers = layers_from_ids(speed_ids(truth, sample.flow, mask), speed_view=True)
            groups.append(VoxelGroup("speed", "speed (|flow|)", offset, _keep(layers, opts)))
        elif name == "error" and truth is not None and pred is not None:
            layers = layers_from_ids(error_ids(truth, pred, mask), error_view=True)
            groups.append(VoxelGroup("error", "error view", offset, _keep(layers, opts)))
    sensor_offset = groups[0].offset if groups else (0.0, 0.0, 0.0)
    return Frame(groups=tuple(groups), sensor_offset=sensor_offset,
                 ego_center=ego_box_center(truth if truth is not None else pred), notes=tuple(notes))
