"""`.pcd` LiDAR files (occdata/nuscenes/pointfiles.py through `load_lidar_points`): the three PCD encodings
written by pypcd4 read to the points we wrote, a hand-written ASCII file to its hand-typed values, per-point
timestamps kept, the planner's count from the header, and each broken file one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pypcd4
import pytest

from occdata.errors import OccDataError
from occdata.nuscenes import load_lidar_points
from occdata.nuscenes.pointfiles import pcd_point_count, read_pcd
from occdata.store.plan import _points

ENCODINGS = (pypcd4.Encoding.ASCII, pypcd4.Encoding.BINARY, pypcd4.Encoding.BINARY_COMPRESSED)


def _cloud(n: int = 257, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyzi = rng.uniform(-60, 60, (n, 4)).astype(np.float32)
    xyzi[:, 3] = rng.integers(0, 256, n)
    times = 1_695_473_372_700_000 + rng.integers(0, 100_000, n).astype(np.uint64)
    return xyzi, times


def _write(path: Path, columns: list[np.ndarray], fields: tuple[str, ...], encoding: pypcd4.Encoding) -> Path:
    pc = pypcd4.PointCloud.from_points(columns, fields, tuple(c.dtype for c in columns))
    pc.save(path, encoding=encoding)
    return path


@pytest.mark.parametrize("encoding", ENCODINGS, ids=lambda e: e.value)
def test_each_encoding_reads_to_the_written_points(tmp_path: Path, encoding: pypcd4.Encoding) -> None:
    xyzi, times = _cloud()
    f = _write(tmp_path / "s.pcd", [*xyzi.T, times], ("x", "y", "z", "intensity", "timestamp"), encoding)
    got = read_pcd(f)
    # ascii keeps pypcd4's printed digits: float32 survives the round trip only to ~1e-5 relative
    tol = 1e-4 if encoding is pypcd4.Encoding.ASCII else 0.0
    np.testing.assert_allclose(got.points[:, :4], xyzi, rtol=tol, atol=0)
    assert got.points.dtype == np.float32 and (got.points[:, 4] == 0).all()  # no ring field: 0
    assert got.timestamps is not None and got.timestamps.dtype == np.uint64
    np.testing.assert_array_equal(got.timestamps, times)
    np.testing.assert_array_equal(load_lidar_points(f), got.points)
    assert pcd_point_count(f) == _points(f) == len(xyzi)


def test_a_hand_written_ascii_file(tmp_path: Path) -> None:
    """Our own bytes (no pypcd4 writer): fields in another order, a ring field, uint8 intensity."""
    text = ("# .PCD v0.7\nVERSION 0.7\nFIELDS intensity ring x y z\nSIZE 1 2 4 4 4\nTYPE U U F F F\n"
            "COUNT 1 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
            "7 3 1.5 -2.25 0.5\n255 31 10 20 -1\n")
    (tmp_path / "h.pcd").write_text(text)
    np.testing.assert_array_equal(load_lidar_points(tmp_path / "h.pcd"),
                                  np.array([[1.5, -2.25, 0.5, 7, 3], [10, 20, -1, 255, 31]], np.float32))
    assert read_pcd(tmp_path / "h.pcd").timestamps is None
    one = text.replace("WIDTH 2", "WIDTH 1").replace("POINTS 2", "POINTS 1").rsplit("255", 1)[0]
    (tmp_path / "one.pcd").write_text(one)
    assert load_lidar_points(tmp_path / "one.pcd").tolist() == [[1.5, -2.25, 0.5, 7.0, 3.0]]


def test_the_planner_counts_pcd_bin_by_size_and_pcd_by_header(tmp_path: Path) -> None:
    (tmp_path / "a.pcd.bin").write_bytes(np.zeros((9, 5), np.float32).tobytes())
    xyzi, _ = _cloud(40)
    _write(tmp_path / "b.pcd", list(xyzi.T), ("x", "y", "z", "intensity"), pypcd4.Encoding.BINARY_COMPRESSED)
    assert (_points(tmp_path / "a.pcd.bin"), _points(tmp_path / "b.pcd"), _points(tmp_path / "none.pcd")) == (9, 40, 0)


def _one_line(path: Path) -> str:
    with pytest.raises(OccDataError) as err:
        load_lidar_points(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    return msg


@pytest.mark.parametrize("encoding", ENCODINGS, ids=lambda e: e.value)
def test_broken_pcd_files_are_one_line(tmp_path: Path, encoding: pypcd4.Encoding) -> None:
    xyzi, times = _cloud(100)
    no_z = _write(tmp_path / "no_z.pcd", [xyzi[:, 0], xyzi[:, 1], xyzi[:, 3]], ("x", "y", "intensity"), encoding)
    assert "PCD field 'z' missing (fields: x, y, intensity)" in _one_line(no_z)
    nan = xyzi.copy()
    nan[42, 1] = np.nan
    bad = _write(tmp_path / "nan.pcd", list(nan.T), ("x", "y", "z", "intensity"), encoding)
    assert "non-finite coordinates at point 42" in _one_line(bad)
    whole = _write(tmp_path / "whole.pcd", [*xyzi.T, times], ("x", "y", "z", "intensity", "timestamp"), encoding)
    raw = whole.read_bytes()
    # ascii: the last line gone (a number cut mid-digit still parses: not detectable); binary: the
    # last 24-byte point gone, and a cut inside a point
    last_line = raw.rstrip(b"\n").rfind(b"\n") + 1
    cuts = (last_line,) if encoding is pypcd4.Encoding.ASCII else (len(raw) - 24, len(raw) - 7)
    for cut in cuts:
        (tmp_path / "cut.pcd").write_bytes(raw[:cut])
        assert "corrupt LiDAR file" in _one_line(tmp_path / "cut.pcd")


def test_broken_headers_are_one_line(tmp_path: Path) -> None:
    (tmp_path / "empty.pcd").write_bytes(b"")
    assert "no PCD header" in _one_line(tmp_path / "empty.pcd")
    head = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F Q\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
            "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2 3\n")
    (tmp_path / "type.pcd").write_text(head)
    assert "invalid PCD header" in _one_line(tmp_path / "type.pcd")
    (tmp_path / "vp.pcd").write_text(head.replace("F F Q", "F F F").replace("VIEWPOINT 0 0 0", "VIEWPOINT 5 0 0"))
    assert "PCD VIEWPOINT 5.0 0.0 0.0 1.0 0.0 0.0 0.0 is not the identity" in _one_line(tmp_path / "vp.pcd")
    assert "missing sensor file" in _one_line(tmp_path / "absent.pcd")
