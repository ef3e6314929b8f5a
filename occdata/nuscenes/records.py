"""Frozen records for the keyframe data that occupancy needs (docs/design.md#frames-and-names), and the LiDAR sweeps."""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, overload

import numpy as np

from occdata.geometry import invert_rigid
from occdata.nuscenes.columns import HashIndex
from occdata.nuscenes.rig import NUSCENES_RIG, Rig

__all__ = ["CameraRecord", "CameraRig", "LazySamples", "LidarRecord", "NuScenesDataset", "SampleRecord", "SceneRecord"]


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


class LazySamples(Sequence[SampleRecord]):
    """A dataset's samples, each record made when it is asked for (`make(base index)`) and dropped
    after: a million keyframes' records took ~7 KiB each; here a sample costs its token's reference.

    `tokens` are the samples' tokens in order (shared with the scene records); `picks` the base
    indices this sequence shows (a selection), `overrides` records that replace the made ones (a
    problem found after reading). The last `_CACHED` records are kept, since callers often ask for
    the same sample several times in a row. Pickled, it becomes a tuple of its records."""

    _CACHED = 64

    def __init__(self, make: Callable[[int], SampleRecord], tokens: Sequence[str], picks: np.ndarray | None = None,
                 overrides: Mapping[int, SampleRecord] | None = None) -> None:
        self._make, self._tokens = make, tokens
        self._picks = np.arange(len(tokens), dtype=np.int64) if picks is None else picks
        self._overrides = dict(overrides or {})
        self._cache: OrderedDict[int, SampleRecord] = OrderedDict()

    def __len__(self) -> int:
        return len(self._picks)

    @overload
    def __getitem__(self, i: int) -> SampleRecord: ...
    @overload
    def __getitem__(self, i: slice) -> LazySamples: ...
    def __getitem__(self, i: int | slice) -> SampleRecord | LazySamples:
        if isinstance(i, slice):
            return self.take(range(len(self))[i])
        return self._record(int(self._picks[i]))  # IndexError past the end ends iteration

    def __iter__(self) -> Iterator[SampleRecord]:
        for base in self._picks:
            yield self._record(int(base))

    def _record(self, base: int) -> SampleRecord:
        if base in self._overrides:
            return self._overrides[base]
        rec = self._cache.get(base)
        if rec is None:
            rec = self._make(base)
            self._cache[base] = rec
            if len(self._cache) > self._CACHED:
                self._cache.popitem(last=False)
        return rec

    def tokens(self) -> list[str]:
        """The samples' tokens, in order, without making their records."""
        return [self._tokens[int(b)] for b in self._picks]

    def take(self, positions: Sequence[int] | np.ndarray) -> LazySamples:
        """The samples at `positions` of this sequence, as a new sequence."""
        picks = self._picks[np.asarray(positions, dtype=np.int64)] if len(positions) else np.zeros(0, np.int64)
        return LazySamples(self._make, self._tokens, picks, self._overrides)

    def with_records(self, records: Mapping[int, SampleRecord]) -> LazySamples:
        """This sequence with the samples at the given positions replaced by `records`."""
        overrides = {**self._overrides, **{int(self._picks[i]): rec for i, rec in records.items()}}
        return LazySamples(self._make, self._tokens, self._picks, overrides)

    def __reduce__(self) -> tuple[Any, ...]:
        return (tuple, (list(self),))


def _tokens_of(samples: Sequence[SampleRecord]) -> list[str]:
    return samples.tokens() if isinstance(samples, LazySamples) else [s.token for s in samples]


@dataclass(frozen=True, eq=False)
class NuScenesDataset:
    """A version folder's keyframes: scenes, and samples in scene order then time order.

    `samples` is a tuple of records, or (from `load_nuscenes`) a `LazySamples` that makes each record
    when asked: iterate or index it, never keep all of its records."""

    root: Path
    version: str
    scenes: tuple[SceneRecord, ...]
    samples: Sequence[SampleRecord]
    warnings: tuple[str, ...] = ()  # one line each: identical duplicate rows, nbr_samples disagreeing
    sweeps_loaded: bool = False  # read with `sweeps=True`: `SampleRecord.sweeps` are filled in
    rig: Rig = NUSCENES_RIG  # the cameras and LiDARs read (`Rig.left_out`: the sensors that were not)
    _tokens: list[str] = field(init=False, repr=False)
    _index: HashIndex = field(init=False, repr=False)

    def __post_init__(self) -> None:
        tokens = _tokens_of(self.samples)
        object.__setattr__(self, "_tokens", tokens)
        object.__setattr__(self, "_index", HashIndex(np.fromiter((hash(t) for t in tokens), np.int64, len(tokens))))

    def __getstate__(self) -> dict[str, Any]:
        # the index holds str hashes, which differ between processes: made again where unpickled
        return {k: v for k, v in vars(self).items() if k not in ("_tokens", "_index")}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for k, v in state.items():
            object.__setattr__(self, k, v)
        self.__post_init__()

    def sample(self, token: str) -> SampleRecord:
        return self.samples[self.index_of(token)]

    def index_of(self, token: str) -> int:
        """Position of a sample token in `samples` (KeyError if absent)."""
        for pos in self._index.candidates(token):
            if self._tokens[pos] == token:
                return pos
        raise KeyError(token)

    def sample_tokens(self) -> list[str]:
        """The samples' tokens in order (no record is made)."""
        return list(self._tokens)

    def split_of(self, sample: SampleRecord) -> str:
        return next(sc.split for sc in self.scenes if sc.token == sample.scene_token)

    def select(self, splits: tuple[str, ...] | None) -> NuScenesDataset:
        """A dataset restricted to scenes whose split is in `splits` (None: everything)."""
        if not splits:
            return self
        return self.only_scenes(tuple(sc for sc in self.scenes if sc.split in splits))

    def only_scenes(self, scenes: tuple[SceneRecord, ...]) -> NuScenesDataset:
        """The dataset of `scenes` (some of this one's, in its order) and their samples."""
        keep = {sc.token for sc in scenes}
        if isinstance(self.samples, LazySamples):
            pos = [self.index_of(t) for sc in self.scenes if sc.token in keep for t in sc.sample_tokens]
            return dataclasses.replace(self, scenes=scenes, samples=self.samples.take(sorted(pos)))
        return dataclasses.replace(self, scenes=scenes, samples=tuple(s for s in self.samples
                                                                       if s.scene_token in keep))

    def with_problems(self, problems: Mapping[int, str]) -> NuScenesDataset:
        """This dataset with sample `i`'s record carrying `problems[i]` (unless it has one already)."""
        if not problems:
            return self
        records = {i: self.samples[i] for i in problems}
        records = {i: r if r.problem else dataclasses.replace(r, problem=problems[i]) for i, r in records.items()}
        if isinstance(self.samples, LazySamples):
            return dataclasses.replace(self, samples=self.samples.with_records(records))
        return dataclasses.replace(self, samples=tuple(records.get(i, s) for i, s in enumerate(self.samples)))

    def scene_slice(self, scene: SceneRecord) -> NuScenesDataset:
        """The dataset of one scene alone (what a task on a worker holds), in `O(scene)` time, its records
        made (a tuple: a task carries them, not the tables). The tree-wide `warnings` stay with the full
        dataset (they are reported once, by the client)."""
        samples = tuple(self.samples[self.index_of(t)] for t in scene.sample_tokens)
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
