"""Keyframe records packed on disk, made again when a sample is asked for (`LazySamples`).

A `SampleRecord` with its 7 sensor records, 13 pose matrices and 7 paths held ~7 KiB as Python
objects; packed, a sensor is its pose's 12 numbers, a shared calibration's index, its timestamp and
size, and its token and path as UTF-8: ~250 bytes, written to a `Spill` (an unnamed temporary file).
In memory a sample keeps 8 bytes (its blob's end), the dataset its calibrations and channel names.
Making a record again costs one read and no table lookup, quaternion or path check (they were done
once, when the tables were read).

A sample's blob: three int64 counts (head, texts, sensor rows), the head (scene, index in scene,
timestamp, cameras, LiDARs, then each LiDAR's sweep count), the texts' byte lengths (int32), the
sensor rows (`_ROW`: cameras, LiDARs, then the sweeps LiDAR by LiDAR) and the texts as UTF-8 (the
sample's token, prev and next, then per sensor its token, path under the root and sample_token).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occdata.nuscenes.records import CameraRecord, LidarRecord, SampleRecord, SceneRecord
from occdata.nuscenes.spill import TEXT_ERRORS as _TEXT
from occdata.nuscenes.spill import Spill

__all__ = ["PackedSamples"]

_ROW = np.dtype([("pose", "<f8", (12,)), ("timestamp", "<i8"), ("calib", "<i4"), ("channel", "<i4"),
                 ("width", "<i4"), ("height", "<i4")])  # pose: T_global_from_ego[:3, :4]


class PackedSamples:
    """`add(record, scene)` in sample order, then `record(k)`: the k-th record made again, equal field
    by field (its pose arrays new, its calibration arrays the shared read-only ones).

    `root` is the dataset root every record path lies under (`dataset_root`)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._root_text = str(root)
        self._spill = Spill()
        self._scenes: list[SceneRecord] = []
        self._channels: list[str] = []
        self._calibs: list[tuple[np.ndarray, np.ndarray | None]] = []
        self._calib_of: dict[tuple[int, int], int] = {}  # ids of the shared (T, K) arrays -> index
        self._problems: dict[int, str] = {}  # placeholder records (rare) keep their problem

    def __len__(self) -> int:
        return len(self._spill)

    def nbytes(self) -> int:
        """Memory held per sample (the blobs' ends), not counting the calibrations and scenes."""
        return self._spill.nbytes()

    def flush(self) -> None:
        """Write what is still buffered (after the last `add`: nothing stays in memory)."""
        self._spill.flush()

    def add(self, rec: SampleRecord, scene: SceneRecord) -> None:
        if not self._scenes or self._scenes[-1] is not scene:
            self._scenes.append(scene)
        if rec.problem:
            self._problems[len(self)] = rec.problem
        lidars = rec.lidars
        sweeps = [rec.sweeps_of(k) for k in range(len(lidars))]
        head = [len(self._scenes) - 1, rec.index_in_scene, rec.timestamp, len(rec.cameras), len(lidars),
                *(len(s) for s in sweeps)]
        sensors: list[CameraRecord | LidarRecord] = [*rec.cameras, *lidars, *(r for s in sweeps for r in s)]
        rows = np.zeros(len(sensors), dtype=_ROW)
        texts = [rec.token, rec.prev, rec.next]
        for i, r in enumerate(sensors):
            row = rows[i]
            row["pose"] = r.T_global_from_ego[:3, :4].ravel()
            row["timestamp"] = r.timestamp
            row["channel"] = self._code(r.channel)
            if isinstance(r, CameraRecord):
                row["calib"] = self._calib(r.T_ego_from_cam, r.K)
                row["width"], row["height"] = r.width, r.height
                texts += (r.token, self._relative(r.path), "")
            else:
                row["calib"] = self._calib(r.T_ego_from_lidar, None)
                texts += (r.token, self._relative(r.path), r.sample_token)
        encoded = [t.encode("utf-8", _TEXT) for t in texts]
        counts = np.array([len(head), len(encoded), len(rows)], dtype="<i8")
        self._spill.add(b"".join((counts.tobytes(), np.array(head, dtype="<i8").tobytes(),
                                  np.array([len(e) for e in encoded], dtype="<i4").tobytes(), rows.tobytes(),
                                  *encoded)))

    def _code(self, channel: str) -> int:
        if channel not in self._channels:
            self._channels.append(channel)
        return self._channels.index(channel)

    def _calib(self, T: np.ndarray, K: np.ndarray | None) -> int:
        key = (id(T), id(K))
        if key not in self._calib_of:  # the reader shares one (T, K) per calibrated_sensor row
            self._calib_of[key] = len(self._calibs)
            self._calibs.append((T, K))
        return self._calib_of[key]

    def _relative(self, path: Path) -> str:
        """`path` under the root as text (string slicing: `Path.relative_to` was half the packing time)."""
        text, root = str(path), self._root_text
        if text == root:
            return ""
        if not text.startswith(root + "/") and not (root.endswith("/") and text.startswith(root)):
            raise ValueError(f"{path} is not under {self.root}")
        return text[len(root.rstrip("/")) + 1:]

    def record(self, k: int) -> SampleRecord:
        blob = self._spill.get(k)
        n_head, n_text, n_rows = np.frombuffer(blob, "<i8", 3).tolist()
        at = 24
        head = np.frombuffer(blob, "<i8", n_head, at).tolist()
        at += 8 * n_head
        ends = np.cumsum(np.frombuffer(blob, "<i4", n_text, at)).tolist()
        at += 4 * n_text
        rows = np.frombuffer(blob, _ROW, n_rows, at)
        at += _ROW.itemsize * n_rows
        text = blob[at:]
        texts = [text[a:b].decode("utf-8", _TEXT) for a, b in zip([0, *ends[:-1]], ends, strict=True)]
        scene_code, index, timestamp, n_cam, n_lid, *sweep_counts = head
        sensors = self._sensors(rows, texts, n_cam)
        sweeps, at = [], n_cam + n_lid
        for count in sweep_counts:
            sweeps.append(tuple(sensors[at:at + count]))
            at += count
        lidars = sensors[n_cam:n_cam + n_lid]
        scene = self._scenes[scene_code]
        return SampleRecord(
            token=texts[0], scene_token=scene.token, scene_name=scene.name, index_in_scene=index, timestamp=timestamp,
            prev=texts[1], next=texts[2], cameras=tuple(sensors[:n_cam]), lidar=lidars[0], sweeps=sweeps[0],
            extra_lidars=tuple(lidars[1:]), extra_sweeps=tuple(sweeps[1:]), problem=self._problems.get(k, ""),
        )

    def _sensors(self, rows: np.ndarray, texts: list[str], n_cam: int) -> list[CameraRecord | LidarRecord]:
        """The sensor records of a blob's `rows` (`_ROW`) and texts (the first `n_cam` rows are cameras)."""
        n = len(rows)
        T_global_from_ego = np.zeros((n, 4, 4))
        T_global_from_ego[:, :3, :4] = rows["pose"].reshape(n, 3, 4)
        T_global_from_ego[:, 3, 3] = 1.0
        stamps, calibs, channels = rows["timestamp"].tolist(), rows["calib"].tolist(), rows["channel"].tolist()
        widths, heights = rows["width"].tolist(), rows["height"].tolist()
        out: list[CameraRecord | LidarRecord] = []
        for i in range(n):
            T_ego_from_sensor, K = self._calibs[calibs[i]]
            token, path, sample_token = texts[3 + 3 * i: 6 + 3 * i]
            channel, T = self._channels[channels[i]], T_global_from_ego[i].copy()
            if i < n_cam:
                out.append(CameraRecord(channel=channel, token=token, path=self.root / path, K=K,
                                        T_ego_from_cam=T_ego_from_sensor, T_global_from_ego=T, timestamp=stamps[i],
                                        width=widths[i], height=heights[i]))
            else:
                out.append(LidarRecord(channel=channel, token=token, path=self.root / path,
                                       T_ego_from_lidar=T_ego_from_sensor, T_global_from_ego=T, timestamp=stamps[i],
                                       sample_token=sample_token))
        return out
