"""LiDAR point files in the PCD format (`.pcd`: ascii, binary, binary_compressed), read through the
maintained `pypcd4` library, as MAN TruckScenes' devkit reads its sweeps.

Our point layout is nuScenes' `.pcd.bin` one: `(N, 5) float32` x, y, z, intensity, ring (lidar
frame). A PCD file names its fields; x, y, z are required, `intensity` and `ring` are taken when
present and are 0 otherwise. A `timestamp` field (TruckScenes: each point's own time, in
microseconds like the tables) is kept as `PcdPoints.timestamps`: `occdata labels --deskew` places
each point by the ego pose of its time (`occdata.labels.deskew`); the build does not use it (it takes
a sweep at its sample_data timestamp, as for nuScenes' files, which have no per-point times).
Problems are one line naming the file and the field or point.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occdata.errors import OccDataError

__all__ = ["PCD_SUFFIX", "PcdPoints", "is_pcd", "pcd_point_count", "read_pcd"]

PCD_SUFFIX = ".pcd"  # nuScenes' `.pcd.bin` is not a PCD file (raw float32 x 5), despite its name
_IDENTITY_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
_HEADER_LINES = 11  # VERSION FIELDS SIZE TYPE COUNT WIDTH HEIGHT VIEWPOINT POINTS DATA (+ slack)


@dataclass(frozen=True, eq=False)
class PcdPoints:
    """One PCD file's points: `points (N, 5) float32` x, y, z, intensity, ring (0 where the file has no
    such field) and `timestamps (N,)` (the file's own `timestamp` field, its own dtype, e.g. TruckScenes'
    uint64 microseconds; None when there is none)."""

    points: np.ndarray
    timestamps: np.ndarray | None

    def __post_init__(self) -> None:
        if self.points.ndim != 2 or self.points.shape[1] != 5 or self.points.dtype != np.float32:
            raise ValueError(f"points must be (N, 5) float32, got {self.points.shape} {self.points.dtype}")
        if self.timestamps is not None and self.timestamps.shape != (len(self.points),):
            raise ValueError(f"timestamps must be ({len(self.points)},), got {self.timestamps.shape}")


def is_pcd(path: Path | str) -> bool:
    """True for a `.pcd` file (and not nuScenes' raw `.pcd.bin`)."""
    return str(path).lower().endswith(PCD_SUFFIX)


def _header(path: Path):  # -> pypcd4.MetaData
    """The parsed header; one line when it is unreadable or invalid."""
    import pypcd4

    lines: list[str] = []
    try:
        with open(path, "rb") as fp:
            for raw in fp:
                line = raw.decode("utf-8", errors="replace").strip()
                if line and not line.startswith("#"):
                    lines.append(line)
                if line.upper().startswith("DATA") or len(lines) >= _HEADER_LINES:
                    break
    except FileNotFoundError:
        raise OccDataError(f"missing sensor file: {path}") from None
    except OSError as exc:
        raise OccDataError(f"cannot read sensor file {path}: {exc.strerror or exc}") from None
    if not lines or not lines[-1].upper().startswith("DATA"):
        raise OccDataError(f"corrupt LiDAR file {path}: no PCD header (no DATA line)")
    try:
        return pypcd4.MetaData.parse_header(lines)
    except Exception as exc:  # pydantic's ValidationError spans lines: keep the first problem
        first = re.sub(r"\s+", " ", str(exc)).strip()[:200]
        raise OccDataError(f"corrupt LiDAR file {path}: invalid PCD header ({first})") from None


def pcd_point_count(path: Path | str) -> int:
    """The POINTS count of a PCD file's header (the build's planner: no data is read)."""
    return int(_header(Path(path)).points)


def read_pcd(path: Path | str) -> PcdPoints:
    """Read a `.pcd` file (any of the three encodings) into our layout; see the module docstring."""
    import pypcd4

    path = Path(path)
    meta = _header(path)
    fields = tuple(meta.fields)
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise OccDataError(f"corrupt LiDAR file {path}: PCD field {missing[0]!r} missing "
                           f"(fields: {', '.join(fields)})")
    for name in ("x", "y", "z", "intensity", "ring", "timestamp"):
        if name in fields and meta.count[fields.index(name)] != 1:
            raise OccDataError(f"corrupt LiDAR file {path}: PCD field {name!r} has COUNT "
                               f"{meta.count[fields.index(name)]}, not 1")
    if tuple(meta.viewpoint) != _IDENTITY_VIEWPOINT:
        # A viewpoint moves the points out of the sensor frame that calibrated_sensor describes.
        raise OccDataError(f"unsupported LiDAR file {path}: PCD VIEWPOINT {' '.join(map(str, meta.viewpoint))} "
                           "is not the identity")
    try:
        data = np.atleast_1d(pypcd4.PointCloud.from_path(path).pc_data)  # ascii, 1 point: 0-d
    except Exception as exc:  # truncated data: numpy's or lzf's error, whatever the encoding
        first = re.sub(r"\s+", " ", str(exc)).strip()[:200]
        raise OccDataError(f"corrupt LiDAR file {path}: PCD data unreadable ({first})") from None
    if len(data) != meta.points:
        raise OccDataError(f"corrupt LiDAR file {path}: PCD header says {meta.points} points, "
                           f"the data holds {len(data)}")
    n = len(data)
    points = np.zeros((n, 5), dtype=np.float32)
    for col, name in enumerate(("x", "y", "z", "intensity", "ring")):
        if name in fields:
            points[:, col] = data[name]
    bad = ~np.isfinite(points[:, :3]).all(axis=1)
    if bad.any():
        raise OccDataError(f"corrupt LiDAR file {path}: non-finite coordinates at point {int(np.argmax(bad))}")
    times = np.ascontiguousarray(data["timestamp"]) if "timestamp" in fields else None
    return PcdPoints(points, times)
