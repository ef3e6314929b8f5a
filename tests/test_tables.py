"""The streaming table reader agrees with json.load across buffer refills and rejects bad JSON."""

from __future__ import annotations

import json

import pytest

from occdata.errors import OccDataError
from occdata.nuscenes.tables import iter_table_rows, load_table


def _rows(n: int) -> list[dict]:
    return [
        {
            "token": f"{i:032x}",
            "translation": [i * 0.5, -1.25, 0.0],
            "rotation": [1.0, 0.0, 0.0, 0.0],
            "camera_intrinsic": [[1266.4, 0.0, 816.2], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]] if i % 2 else [],
            "name": "s \u00e9 \"quoted\" ]}, tricky",
            "is_key_frame": i % 3 == 0,
        }
        for i in range(n)
    ]


@pytest.mark.parametrize("indent", [None, 2])
def test_streaming_matches_json_load_over_many_chunks(tmp_path, indent) -> None:
    rows = _rows(12_000)  # several MB: forces buffer refills inside rows
    path = tmp_path / "t.json"
    path.write_text(json.dumps(rows, indent=indent))
    assert path.stat().st_size > 2 * (1 << 20)
    assert list(iter_table_rows(path)) == rows
    kept = load_table(path, keep=lambda r: r["is_key_frame"])
    assert list(kept) == [r["token"] for r in rows if r["is_key_frame"]]


def test_empty_array(tmp_path) -> None:
    path = tmp_path / "t.json"
    path.write_text(" [ ] \n")
    assert list(iter_table_rows(path)) == []


@pytest.mark.parametrize(
    "text",
    ['[{"token": "a"},]', '[{"token": "a"} {"token": "b"}]', '[{"token": "a"}] x', "[1, 2]", "", "[", '{"a": 1}'],
)
def test_malformed(tmp_path, text: str) -> None:
    path = tmp_path / "t.json"
    path.write_text(text)
    with pytest.raises(OccDataError, match="malformed JSON in .*t.json"):
        list(iter_table_rows(path))


def test_malformed_late_in_big_file(tmp_path) -> None:
    text = json.dumps(_rows(12_000))
    path = tmp_path / "t.json"
    path.write_text(text[:-40] + "@@" + text[-38:])
    with pytest.raises(OccDataError, match="malformed JSON"):
        list(iter_table_rows(path))
