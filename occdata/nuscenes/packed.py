"""Keyframe records packed into columns, made again when a sample is asked for (`LazySamples`).

A `SampleRecord` with its 7 sensor records, 13 pose matrices and 7 paths held ~7 KiB as Python
objects; packed, a sensor is its pose's 12 numbers, a shared calibration's index, its timestamp and
size, and its token and path as UTF-8 in shared buffers: ~250 bytes. Making a record again costs no
table lookup, quaternion or path check (they were done once, when the tables were read).
"""

from __future__ import annotations

from array import array
from pathlib import Path

import numpy as np

from occdata.nuscenes.columns import TextColumn
from occdata.nuscenes.records import CameraRecord, LidarRecord, SampleRecord, SceneRecord

__all__ = ["PackedSamples"]


class _Sensors:
    """Camera and LiDAR records as columns (a camera's `sample_token` is "", a LiDAR's size 0 x 0)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._root_text = str(root)
        self.channels: list[str] = []
        self.channel = array("h")
        self.token, self.path, self.sample_token = TextColumn(), TextColumn(), TextColumn()
        self.pose = array("d")  # T_global_from_ego[:3, :4], 12 a row
        self.calib = array("i")  # index into `calibs`
        self.calibs: list[tuple[np.ndarray, np.ndarray | None]] = []
        self._calib_of: dict[tuple[int, int], int] = {}  # ids of the shared (T, K) arrays -> index
        self.timestamp = array("q")
        self.size = array("i")  # width, height

    def __len__(self) -> int:
        return len(self.channel)

    def _code(self, channel: str) -> int:
        if channel not in self.channels:
            self.channels.append(channel)
        return self.channels.index(channel)

    def _calib(self, T: np.ndarray, K: np.ndarray | None) -> int:
        key = (id(T), id(K))
        if key not in self._calib_of:  # the reader shares one (T, K) per calibrated_sensor row
            self._calib_of[key] = len(self.calibs)
            self.calibs.append((T, K))
        return self._calib_of[key]

    def add_camera(self, c: CameraRecord) -> None:
        self._add(c.channel, c.token, c.path, c.T_global_from_ego, self._calib(c.T_ego_from_cam, c.K), c.timestamp,
                  c.width, c.height, "")

    def add_lidar(self, r: LidarRecord) -> None:
        self._add(r.channel, r.token, r.path, r.T_global_from_ego, self._calib(r.T_ego_from_lidar, None), r.timestamp,
                  0, 0, r.sample_token)

    def _add(self, channel: str, token: str, path: Path, T: np.ndarray, calib: int, timestamp: int, width: int,
             height: int, sample_token: str) -> None:
        self.channel.append(self._code(channel))
        self.token.append(token)
        self.path.append(self._relative(path))
        self.pose.extend(T[:3, :4].ravel().tolist())
        self.calib.append(calib)
        self.timestamp.append(timestamp)
        self.size.extend((width, height))
        self.sample_token.append(sample_token)

    def _relative(self, path: Path) -> str:
        """`path` under the root as text (string slicing: `Path.relative_to` was half the packing time)."""
        text, root = str(path), self._root_text
        if text == root:
            return ""
        if not text.startswith(root + "/") and not (root.endswith("/") and text.startswith(root)):
            raise ValueError(f"{path} is not under {self.root}")
        return text[len(root.rstrip("/")) + 1:]

    def _T(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :4] = np.frombuffer(self.pose, dtype=np.float64, count=12, offset=96 * i).reshape(3, 4)
        return T

    def camera(self, i: int) -> CameraRecord:
        T_ego_from_cam, K = self.calibs[self.calib[i]]
        return CameraRecord(channel=self.channels[self.channel[i]], token=self.token.get(i),
                            path=self.root / self.path.get(i), K=K, T_ego_from_cam=T_ego_from_cam,
                            T_global_from_ego=self._T(i), timestamp=self.timestamp[i], width=self.size[2 * i],
                            height=self.size[2 * i + 1])

    def lidar(self, i: int) -> LidarRecord:
        return LidarRecord(channel=self.channels[self.channel[i]], token=self.token.get(i),
                           path=self.root / self.path.get(i), T_ego_from_lidar=self.calibs[self.calib[i]][0],
                           T_global_from_ego=self._T(i), timestamp=self.timestamp[i],
                           sample_token=self.sample_token.get(i))


class PackedSamples:
    """`add(record, scene)` in sample order, then `record(k)`: the k-th record made again, equal field
    by field (its pose arrays new, its calibration arrays the shared read-only ones).

    `root` is the dataset root every record path lies under (`dataset_root`)."""

    def __init__(self, root: Path) -> None:
        self._sensors = _Sensors(root)
        self._scenes: list[SceneRecord] = []
        self._scene = array("i")
        self._index = array("i")
        self._timestamp = array("q")
        self._token, self._prev, self._next = TextColumn(), TextColumn(), TextColumn()
        self._first = array("q")  # the sample's first sensor row: cameras, then LiDARs, then sweeps
        self._shape = array("i")  # cameras, LiDARs
        self._n_sweeps = array("i")  # per sample and LiDAR, flat; `_sweep_at` the sample's first
        self._sweep_at = array("q")
        self._problems: dict[int, str] = {}  # placeholder records (rare) keep their problem

    def __len__(self) -> int:
        return len(self._scene)

    def add(self, rec: SampleRecord, scene: SceneRecord) -> None:
        if not self._scenes or self._scenes[-1] is not scene:
            self._scenes.append(scene)
        self._scene.append(len(self._scenes) - 1)
        self._index.append(rec.index_in_scene)
        self._timestamp.append(rec.timestamp)
        self._token.append(rec.token)
        self._prev.append(rec.prev)
        self._next.append(rec.next)
        self._first.append(len(self._sensors))
        self._sweep_at.append(len(self._n_sweeps))
        if rec.problem:
            self._problems[len(self._scene) - 1] = rec.problem
        self._shape.extend((len(rec.cameras), len(rec.lidars)))
        for c in rec.cameras:
            self._sensors.add_camera(c)
        for r in rec.lidars:
            self._sensors.add_lidar(r)
        for k in range(len(rec.lidars)):
            sweeps = rec.sweeps_of(k)
            self._n_sweeps.append(len(sweeps))
            for r in sweeps:
                self._sensors.add_lidar(r)

    def record(self, k: int) -> SampleRecord:
        n_cam, n_lid = self._shape[2 * k], self._shape[2 * k + 1]
        row = self._first[k]
        sweep_counts = self._n_sweeps[self._sweep_at[k]:self._sweep_at[k] + n_lid].tolist()
        cams = tuple(self._sensors.camera(row + i) for i in range(n_cam))
        row += n_cam
        lidars = [self._sensors.lidar(row + i) for i in range(n_lid)]
        row += n_lid
        sweeps = []
        for count in sweep_counts:
            sweeps.append(tuple(self._sensors.lidar(row + i) for i in range(count)))
            row += count
        scene = self._scenes[self._scene[k]]
        return SampleRecord(
            token=self._token.get(k), scene_token=scene.token, scene_name=scene.name, index_in_scene=self._index[k],
            timestamp=self._timestamp[k], prev=self._prev.get(k), next=self._next.get(k), cameras=cams,
            lidar=lidars[0], sweeps=sweeps[0], extra_lidars=tuple(lidars[1:]), extra_sweeps=tuple(sweeps[1:]),
            problem=self._problems.get(k, ""),
        )
