"""What the viewer reads: the scenes of a store (through `StoreReader`) and the prediction files (through
`occdata.eval.evaluate`'s reader), one sample at a time. No viser, no torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occdata.constants import GRID
from occdata.errors import OccDataError
from occdata.eval.evaluate import find_predictions
from occdata.formats.occ3d import read_prediction
from occdata.store.layout import STATE_DONE
from occdata.store.reader import StoreReader, open_store
from occdata.view.voxels import FrustumParams, frustum_params, lift_depth_points

__all__ = ["MASK_ARRAYS", "SampleData", "SceneEntry", "ViewSource"]

# Mask choices: label -> (per-sample array, the flag array saying the sample has it).
MASK_ARRAYS: dict[str, tuple[str, str]] = {
    "camera": ("labels/mask_camera", "labels/present"),
    "lidar": ("labels/mask_lidar", "labels/present"),
    "camera (occdata visibility)": ("visibility/camera", "visibility/present"),
    "lidar (occdata visibility)": ("visibility/lidar", "visibility/present"),
}
_MAX_IMAGE_WIDTH = 480  # camera images are decoded at 1/2^k scale down to about this width


@dataclass(frozen=True)
class SceneEntry:
    """A scene as the viewer lists it: `indices` are its committed store indices in time order."""

    name: str
    split: str
    indices: tuple[int, ...]

    @property
    def title(self) -> str:
        return f"{self.name} ({self.split}, {len(self.indices)} keyframes)"


@dataclass(frozen=True, eq=False)
class SampleData:
    """One keyframe as the viewer needs it.

    `semantics (X, Y, Z) uint8` (None without labels); `masks`: name -> `(X, Y, Z) uint8` 0/1 (only those
    the sample has); `pred (X, Y, Z) uint8` (None without a prediction); `cameras`: frustum per camera;
    `images`: RGB `(h, w, 3) uint8` per camera (decoded small; None unless asked for);
    `points_ego (M, 3) float32`: the stored depth points of all cameras lifted to key ego (None unless
    asked for); `flow (X, Y, Z, 2) float32` (vx, vy) m/s (None unless asked for and the store has it)."""

    index: int
    token: str
    scene: str
    position: int  # index of the keyframe in its scene
    n_in_scene: int
    semantics: np.ndarray | None
    masks: dict[str, np.ndarray]
    pred: np.ndarray | None
    camera_names: tuple[str, ...]
    cameras: tuple[FrustumParams, ...]
    images: tuple[np.ndarray, ...] | None = None
    points_ego: np.ndarray | None = None
    flow: np.ndarray | None = None


class ViewSource:
    """The store (and optional prediction folder) behind a viewer, restricted to `split` (None: all)."""

    def __init__(self, store: str | Path, pred: Path | None = None, split: str | None = None) -> None:
        self.reader: StoreReader = open_store(store)
        if self.reader.grid.grid != GRID:  # the viewer draws on Occ3D's grid
            raise OccDataError(f"{store}: its labels are on grid {self.reader.grid.name}; occdata view shows "
                               "stores on Occ3D's grid only (not yet other grids)")
        self.split = split
        self.predictions: dict[str, Path] = find_predictions(pred) if pred is not None else {}
        self.has_pred_folder = pred is not None
        self.scenes: tuple[SceneEntry, ...] = self._list_scenes()

    def _list_scenes(self) -> tuple[SceneEntry, ...]:
        r = self.reader
        names = list(r.attrs.get("splits", []))
        keep = r.state == STATE_DONE
        if self.split is not None:
            keep &= np.isin(r.small("sample/split"), [names.index(self.split)] if self.split in names else [])
        scene_index = r.small("sample/scene_index")
        position = r.small("sample/index_in_scene")
        out = []
        for k, scene in enumerate(r.attrs.get("scenes", [])):
            idx = np.flatnonzero(keep & (scene_index == k))
            if idx.size:
                idx = idx[np.argsort(position[idx], kind="stable")]
                out.append(SceneEntry(name=str(scene["name"]), split=str(scene.get("split", "")),
                                      indices=tuple(int(i) for i in idx)))
        return tuple(out)

    def empty_reason(self) -> str:
        """Why there is nothing to show, in words ("" when there is)."""
        if self.scenes:
            return ""
        splits = ", ".join(self.reader.attrs.get("splits", [])) or "none"
        if self.split is not None:
            return (f"No samples to show: split '{self.split}' has no built samples in {self.reader.path} "
                    f"(its splits: {splits}).")
        return f"No samples to show: {self.reader.path} has no built samples."

    def has_labels(self) -> bool:
        """Whether any listed sample has Occ3D labels."""
        present = self.reader.small("labels/present").astype(bool)
        return any(bool(present[list(s.indices)].any()) for s in self.scenes)

    def scene(self, name: str) -> SceneEntry:
        for s in self.scenes:
            if s.name == name:
                return s
        known = ", ".join(s.name for s in self.scenes[:8]) or "none"
        raise OccDataError(f"scene '{name}' is not among the viewable scenes of {self.reader.path} ({known})")

    def _masks(self, index: int) -> dict[str, np.ndarray]:
        out = {}
        for name, (array, flag) in MASK_ARRAYS.items():
            if bool(self.reader.small(flag)[index]):
                out[name] = self.reader.sample_arrays(index, (array,))[array]
        return out

    def _cameras(self, index: int) -> tuple[FrustumParams, ...]:
        a = self.reader.sample_arrays(index, ("calib/K", "calib/T_keyego_from_cam", "cam/image_size"))
        return tuple(frustum_params(K, tuple(size), T) for K, size, T in
                     zip(a["calib/K"], a["cam/image_size"], a["calib/T_keyego_from_cam"], strict=True))

    def _images(self, index: int) -> tuple[np.ndarray, ...]:
        width = int(self.reader.small("cam/image_size")[index, :, 0].max())
        scale = float(self.reader.attrs.get("images", {}).get("scale", 1.0)) or 1.0
        reduce = 1
        while reduce < 8 and width * scale / (2 * reduce) >= _MAX_IMAGE_WIDTH:
            reduce *= 2
        return tuple(self.reader.images(index, reduce=reduce))

    def _points(self, index: int) -> np.ndarray:
        a = self.reader.sample_arrays(index, ("calib/K", "calib/T_keyego_from_cam"))
        parts = [lift_depth_points(uvd, K, T) for uvd, K, T in
                 zip(self.reader.depth_points(index), a["calib/K"], a["calib/T_keyego_from_cam"], strict=True)]
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)

    def prediction(self, token: str) -> np.ndarray | None:
        path = self.predictions.get(token)
        return read_prediction(path) if path is not None else None

    @property
    def has_flow(self) -> bool:
        """Whether the store holds `labels/flow` (the speed view)."""
        return self.reader.has_flow

    def sample(self, scene: SceneEntry, position: int, images: bool = False, points: bool = False,
               flow: bool = False) -> SampleData:
        """The keyframe at `position` (0-based) of `scene`; images, LiDAR points and flow only when asked."""
        if not 0 <= position < len(scene.indices):
            raise OccDataError(f"keyframe {position} out of range: {scene.name} has {len(scene.indices)}")
        index = scene.indices[position]
        r = self.reader
        r.require_done(index)
        token = r.token(index)
        labelled = bool(r.small("labels/present")[index])
        semantics = r.sample_arrays(index, ("labels/semantics",))["labels/semantics"] if labelled else None
        return SampleData(
            index=index, token=token, scene=scene.name, position=position, n_in_scene=len(scene.indices),
            semantics=semantics, masks=self._masks(index), pred=self.prediction(token),
            camera_names=tuple(r.attrs.get("camera_order", ())), cameras=self._cameras(index),
            images=self._images(index) if images else None,
            points_ego=self._points(index) if points else None,
            flow=(r.sample_arrays(index, ("labels/flow",))["labels/flow"]
                  if flow and labelled and r.has_flow else None),
        )
