"""Issue 48.8: untrusted inputs cannot make us allocate or read without bound.

- A `.pcd` header is checked before anything is allocated from it: POINTS against WIDTH x HEIGHT
  and against the file's size; binary_compressed's two sizes against the header and the file
  before decompressing; the header is read from a bounded prefix (a file without newlines is not
  read whole). Reads are counted, never timed.
- The JSON table reader stops at a bad row without reading on (was: 1 MB refills to the end).
- Samples that carry different sensors: one line naming the channel and the rig options.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pypcd4
import pytest
from test_input_hardening import build, edit_table, one_error_line, world  # noqa: F401 - world: a fixture

import occdata.nuscenes.pointfiles as pointfiles
import occdata.nuscenes.tables as tables
from occdata.errors import OccDataError
from occdata.nuscenes.pointfiles import pcd_point_count, read_pcd
from occdata.nuscenes.tables import iter_table_rows
from occdata.store.plan import _points

HEAD = ("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {w}\n"
        "HEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {enc}\n")


def _pcd(path: Path, n: int, w: int, h: int = 1, enc: str = "binary", data: bytes = b"") -> Path:
    path.write_bytes(HEAD.format(n=n, w=w, h=h, enc=enc).encode() + data)
    return path


class _Counted:
    """A file object that counts what is read from it (bytes or characters), through read or lines."""

    def __init__(self, fh: Any, tally: list[int]) -> None:
        self.fh, self.tally = fh, tally

    def read(self, n: int = -1) -> Any:
        out = self.fh.read(n)
        self.tally[0] += len(out)
        return out

    def __iter__(self) -> Any:
        for line in self.fh:
            self.tally[0] += len(line)
            yield line

    def __getattr__(self, name: str) -> Any:
        return getattr(self.fh, name)

    def __enter__(self) -> _Counted:
        return self

    def __exit__(self, *exc: object) -> None:
        self.fh.close()


def _count_reads(monkeypatch, module: Any) -> list[int]:
    tally = [0]
    monkeypatch.setattr(module, "open", lambda *a, **k: _Counted(open(*a, **k), tally), raising=False)
    return tally


# --- .pcd headers -----------------------------------------------------------------------------------
def test_points_beyond_width_times_height_names_the_file(tmp_path: Path) -> None:
    """Was: POINTS 10^19 with WIDTH 1 x HEIGHT 1 parsed, and the planner overflowed int64 ("unexpected
    OverflowError ... at plan.py:89", no file named)."""
    f = _pcd(tmp_path / "huge.pcd", 10**19, 1, data=np.zeros(4, np.float32).tobytes())
    with pytest.raises(OccDataError, match=r"huge\.pcd: PCD header says POINTS 10000000000000000000, but "
                                           r"WIDTH x HEIGHT is 1 x 1"):
        pcd_point_count(f)
    assert _points(f) == 0  # the planner: unreadable now, the sample fails on its own line
    with pytest.raises(OccDataError, match="huge.pcd"):
        read_pcd(f)


def test_points_beyond_the_file_size_names_the_file(tmp_path: Path) -> None:
    """Was: POINTS 1e9 (WIDTH 1e9) in a 200-byte file planned 1e9 points a camera for that sample."""
    f = _pcd(tmp_path / "big.pcd", 10**9, 10**9, data=np.zeros((2, 4), np.float32).tobytes())
    with pytest.raises(OccDataError, match=r"big\.pcd: PCD header says 1000000000 points \(16000000000 bytes\), "
                                           r"the file holds 32 bytes"):
        pcd_point_count(f)
    assert _points(f) == 0
    a = _pcd(tmp_path / "a.pcd", 10**9, 10**9, enc="ascii", data=b"1 2 3 4\n")
    with pytest.raises(OccDataError, match=r"a\.pcd: .* more than its 8 bytes of ascii data"):
        pcd_point_count(a)


def test_compressed_sizes_are_checked_before_decompressing(tmp_path: Path, monkeypatch) -> None:
    """Was: pypcd4 handed the header's uncompressed size (up to 4 GiB) to lzf before any check."""
    import lzf

    calls: list[int] = []
    real = lzf.decompress
    monkeypatch.setattr(lzf, "decompress", lambda data, size: calls.append(size) or real(data, size))
    n = 100
    for name, sizes in (("claims4g.pcd", (10, 2**32 - 1)),  # the header says 100 x 16 = 1600 bytes
                        ("beyond.pcd", (10**6, n * 16)),  # more compressed bytes than the file has
                        ("ratio.pcd", (10, n * 16))):  # 1600 bytes from 10: no LZF stream does that
        f = _pcd(tmp_path / name, n, n, enc="binary_compressed", data=struct.pack("<II", *sizes) + b"\0" * 10)
        with pytest.raises(OccDataError, match=rf"{name}: binary_compressed sizes"):
            read_pcd(f)
        with pytest.raises(OccDataError, match=name):
            pcd_point_count(f)
    assert calls == []
    good = tmp_path / "good.pcd"
    xyz = np.arange(3 * 300, dtype=np.float32).reshape(300, 3)
    pypcd4.PointCloud.from_points(list(xyz.T), ("x", "y", "z"), (np.float32,) * 3).save(
        good, encoding=pypcd4.Encoding.BINARY_COMPRESSED)
    np.testing.assert_array_equal(read_pcd(good).points[:, :3], xyz)
    assert calls == [300 * 12]


def test_a_header_without_newline_is_read_to_a_bound(tmp_path: Path, monkeypatch) -> None:
    """Was: the header loop iterated the file by lines: 8 MB without a newline were read as one line."""
    f = tmp_path / "noline.pcd"
    f.write_bytes(b"VERSION 0.7 " + b"A" * (8 << 20))
    tally = _count_reads(monkeypatch, pointfiles)
    with pytest.raises(OccDataError, match=r"noline\.pcd: no PCD header \(no DATA line in its first 64 KiB\)"):
        pcd_point_count(f)
    assert 0 < tally[0] <= 64 * 1024, tally


# --- the JSON table reader --------------------------------------------------------------------------
def test_a_bad_row_stops_the_table_reader_without_reading_on(tmp_path: Path, monkeypatch) -> None:
    """Was: a row that does not decode refilled the window 1 MB at a time to the end of the file
    (each refill copying the window: quadratic), then failed. 24 MB after a bad second row: the
    reader now reads one window."""
    path = tmp_path / "sample_data.json"
    good = ', '.join(json.dumps({"token": f"t{i:06d}", "pad": "x" * 200}) for i in range(120_000))
    path.write_text('[{"token": "a"}, {"token": "b", oops}, ' + good + "]")
    assert path.stat().st_size > 24 << 20
    tally = _count_reads(monkeypatch, tables)
    with pytest.raises(OccDataError, match=r"malformed JSON in .*sample_data\.json: Expecting property name "
                                           r"enclosed in double quotes at character 32"):
        list(iter_table_rows(path))
    assert tally[0] <= 2 * tables._CHUNK, tally


def test_rows_longer_than_a_window_and_cut_values_still_read(tmp_path: Path, monkeypatch) -> None:
    """The refills that complete a long row double the window; values cut at a window's end (a literal,
    a number, an escape) are completed, not reported."""
    monkeypatch.setattr(tables, "_CHUNK", 64)
    rows = [{"token": "t0", "long": "y" * 5000}, {"token": "t1", "ok": True, "n": 1.25e5, "s": "\u00e9\\"}]
    rows += [{"token": f"t{i}", "v": None, "w": -17} for i in range(2, 60)]
    path = tmp_path / "t.json"
    path.write_text(json.dumps(rows))
    assert list(iter_table_rows(path)) == rows
    path.write_text(json.dumps(rows, ensure_ascii=True))
    assert list(iter_table_rows(path)) == rows


# --- samples that carry different sensors -----------------------------------------------------------
def test_a_sample_missing_a_sensor_names_it_and_the_rig_options(world: Path, tmp_path: Path) -> None:  # noqa: F811
    """Was: "sample ... has no keyframe sample_data for CAM_BACK", with no hint of --cameras."""
    def drop_cam_back(rows: list[dict]) -> None:
        tok = json.loads((world / "v1.0-mini" / "sample.json").read_text())[1]["token"]
        row = next(r for r in rows if r["sample_token"] == tok and "/CAM_BACK/" in r["filename"] and r["is_key_frame"])
        row["is_key_frame"] = False

    edit_table(world, "sample_data", drop_cam_back)
    code, text = build(world, tmp_path / "s.zarr")
    line = one_error_line(code, text, "no keyframe sample_data for CAM_BACK", "--cameras ")
    hint = line.split("--cameras ", 1)[1].split()[0].split(",")  # the cameras this sample has
    assert "CAM_BACK" not in hint and "CAM_FRONT" in hint, line
    assert "--lidars" not in line
