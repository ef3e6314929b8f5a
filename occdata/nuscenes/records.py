"""Frozen records for the keyframe data that occupancy needs (docs/design.md#frames-and-names), and the LiDAR sweeps."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occdata.geometry import invert_rigid
from occdata.nuscenes.rig import NUSCENES_RIG, Rig

__all__ = ["CameraRecord", "CameraRig", "LidarRecord", "NuScenesDataset", "SampleRecord", "SceneRecord"]


@dataclass(frozen=True, eq=False)
class CameraRecord:
    """One camera image of a keyframe.

    `K (3, 3) float64`; `T_ego_from_cam (4, 4) float64` (calibrated_sensor);
    `T_global_from_ego (4, 4) float64` (ego pose at the camera's own timestamp).
    """

    channel: str
    token: str  # sample_data token
    path: Path  # absolute
    K: np.ndarray
    T_ego_from_cam: np.ndarray
    T_global_from_ego: np.ndarray
    timestamp: int  # microseconds
    width: int
    height: int


@dataclass(frozen=True, eq=False)
class CameraRig:
    """A keyframe's cameras in its key-ego frame, in the rig's order: `K (N, 3, 3) float64`,
    `T_keyego_from_cam (N, 4, 4) float64` (exact, through global), `image_size (N, 2) int64` (W, H).
    Built in one place (`SampleRecord.camera_rig`) for the store, the masks and the deploy rig."""

    K: np.ndarray
    T_keyego_from_cam: np.ndarray
    image_size: np.ndarray
    channels: tuple[str, ...]

    @property
    def T_cam_from_keyego(self) -> np.ndarray:
        """`(N, 4, 4) float64`: key ego -> each camera."""
        return np.stack([invert_rigid(T) for T in self.T_keyego_from_cam])


@dataclass(frozen=True, eq=False)
class LidarRecord:
    """One LiDAR sweep: a keyframe's (the reference LiDAR's ego pose defines the sample's key-ego
    frame) or a non-keyframe sweep (`SampleRecord.sweeps`). `T_ego_from_lidar`, `T_global_from_ego`:
    `(4, 4) float64`, the latter at the sweep's own timestamp (microseconds)."""

    channel: str
    token: str  # sample_data token
    path: Path  # absolute
    T_ego_from_lidar: np.ndarray
    T_global_from_ego: np.ndarray
    timestamp: int
    # The row's sample_token: the keyframe's own sample; for a non-keyframe sweep the sample it is
    # filed under in sample_data.json (in nuScenes the NEXT keyframe's).
    sample_token: str = ""


@dataclass(frozen=True, eq=False)
class SampleRecord:
    """A keyframe sample: its cameras in the rig's order, the reference LiDAR's keyframe sweep
    (`lidar`) and the other LiDARs' (`extra_lidars`, rig order)."""

    token: str
    scene_token: str
    scene_name: str
    index_in_scene: int
    timestamp: int
    prev: str
    next: str
    cameras: tuple[CameraRecord, ...]
    lidar: LidarRecord
    # Why the tables cannot describe this sample (a non-numeric field, a path outside the root, ...);
    # "" when fine. Such a record holds NaN placeholders and `validate_sample` rejects it, so the
    # problem stays with this one sample (and `--on-error skip` applies to it).
    problem: str = ""
    # The non-keyframe LIDAR_TOP sweeps since the previous keyframe's LIDAR_TOP (for the scene's
    # first keyframe: back to the start of its chain), nearest first. Empty unless the tables were
    # read with `sweeps=True`. `NuScenesDataset.lidar_history` continues across earlier keyframes.
    sweeps: tuple[LidarRecord, ...] = ()
    # The rig's other LiDARs at this keyframe (their keyframe rows), and for each of them its non-keyframe
    # sweeps since the previous keyframe, as `sweeps` is for the reference LiDAR.
    extra_lidars: tuple[LidarRecord, ...] = ()
    extra_sweeps: tuple[tuple[LidarRecord, ...], ...] = ()

    @property
    def lidars(self) -> tuple[LidarRecord, ...]:
        """Every LiDAR's keyframe sweep, the reference first."""
        return (self.lidar, *self.extra_lidars)

    def sweeps_of(self, k: int) -> tuple[LidarRecord, ...]:
        """The non-keyframe sweeps of LiDAR `k` (rig order; 0 = reference) since the previous keyframe."""
        return self.sweeps if k == 0 else self.extra_sweeps[k - 1]

    @property
    def T_global_from_keyego(self) -> np.ndarray:
        """`(4, 4) float64`: key ego (ego at the LiDAR keyframe timestamp) -> global."""
        return self.lidar.T_global_from_ego

    def T_keyego_from_cam(self, i: int) -> np.ndarray:
        """Exact camera -> key-ego transform through global (docs/design.md#frames-and-names), `(4, 4) float64`."""
        cam = self.cameras[i]
        return invert_rigid(self.T_global_from_keyego) @ cam.T_global_from_ego @ cam.T_ego_from_cam

    def camera_rig(self) -> CameraRig:
        """The cameras' intrinsics, key-ego poses and image sizes (`CameraRig`)."""
        return CameraRig(
            K=np.stack([c.K for c in self.cameras]),
            T_keyego_from_cam=np.stack([self.T_keyego_from_cam(i) for i in range(len(self.cameras))]),
            image_size=np.array([[c.width, c.height] for c in self.cameras], dtype=np.int64),
            channels=tuple(c.channel for c in self.cameras),
        )

    def T_cam_from_lidar(self, i: int, sweep: LidarRecord | None = None) -> np.ndarray:
        """The devkit's chain lidar(t_i) -> ego(t_i) -> global -> ego(t_cam) -> camera, `(4, 4) float64`,
        for the keyframe sweep or another `sweep` (its own calibration and ego pose)."""
        cam = self.cameras[i]
        lidar = self.lidar if sweep is None else sweep
        return (
            invert_rigid(cam.T_ego_from_cam)
            @ invert_rigid(cam.T_global_from_ego)
            @ lidar.T_global_from_ego
            @ lidar.T_ego_from_lidar
        )


@dataclass(frozen=True, eq=False)
class SceneRecord:
    token: str
    name: str
    description: str
    log_token: str
    location: str
    split: str  # train/val/test, mini_train/mini_val, or a tag from the description; "unassigned"
    sample_tokens: tuple[str, ...]  # time order


@dataclass(frozen=True, eq=False)
class NuScenesDataset:
    """A version folder's keyframes: scenes, and samples in scene order then time order."""

    root: Path
    version: str
    scenes: tuple[SceneRecord, ...]
    samples: tuple[SampleRecord, ...]
    warnings: tuple[str, ...] = ()  # one line each: identical duplicate rows, nbr_samples disagreeing
    sweeps_loaded: bool = False  # read with `sweeps=True`: `SampleRecord.sweeps` are filled in
    rig: Rig = NUSCENES_RIG  # the cameras and LiDARs read (`Rig.left_out`: the sensors that were not)
    _index: dict[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_index", {s.token: i for i, s in enumerate(self.samples)})

    def sample(self, token: str) -> SampleRecord:
        return self.samples[self._index[token]]

    def index_of(self, token: str) -> int:
        """Position of a sample token in `samples` (KeyError if absent)."""
        return self._index[token]

    def split_of(self, sample: SampleRecord) -> str:
        return next(sc.split for sc in self.scenes if sc.token == sample.scene_token)

    def select(self, splits: tuple[str, ...] | None) -> NuScenesDataset:
        """A dataset restricted to scenes whose split is in `splits` (None: everything)."""
        if not splits:
            return self
        scenes = tuple(sc for sc in self.scenes if sc.split in splits)
        keep = {sc.token for sc in scenes}
        return dataclasses.replace(
            self, scenes=scenes, samples=tuple(s for s in self.samples if s.scene_token in keep)
        )

    def scene_slice(self, scene: SceneRecord) -> NuScenesDataset:
        """The dataset of one scene alone (what a task on a worker holds), in `O(scene)` time.
        The tree-wide `warnings` stay with the full dataset (they are reported once, by the client)."""
        samples = tuple(self.samples[self._index[t]] for t in scene.sample_tokens)
        return dataclasses.replace(self, scenes=(scene,), samples=samples, warnings=())

    def lidar_history(self, index: int, n: int) -> tuple[LidarRecord, ...]:
        """Up to `n` LIDAR_TOP sweeps before sample `index`'s keyframe sweep, nearest first: its own
        `sweeps`, then the previous keyframe's LIDAR_TOP and that keyframe's sweeps, and so on back
        to the start of the scene's chain (fewer than `n` there). The keyframe sweep itself is not
        included. Requires `sweeps_loaded` when `n > 0`."""
        if n <= 0:
            return ()
        return self._history(index, n, 0)

    def lidar_histories(self, index: int, n: int) -> tuple[LidarRecord, ...]:
        """`lidar_history` for every LiDAR of the rig, in rig order, concatenated: up to `n` previous
        sweeps of each (for nuScenes' one LiDAR, exactly `lidar_history`)."""
        if n <= 0:
            return ()
        return tuple(r for k in range(len(self.rig.lidars)) for r in self._history(index, n, k))

    def _history(self, index: int, n: int, k: int) -> tuple[LidarRecord, ...]:
        if not self.sweeps_loaded:
            raise ValueError("lidar_history needs the tables read with sweeps=True")
        out = list(self.samples[index].sweeps_of(k))
        j = index
        while len(out) < n and self.samples[j].index_in_scene > 0:
            j -= 1
            out.append(self.samples[j].lidars[k])
            out.extend(self.samples[j].sweeps_of(k))
        return tuple(out[:n])
