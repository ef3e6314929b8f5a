"""Streaming reader for nuScenes JSON tables.

The trainval `sample_data.json` and `ego_pose.json` hold millions of rows; parsing them whole costs
several GB. Rows are decoded one at a time from a bounded buffer and filtered on the fly, so memory
stays proportional to the rows kept.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from occdata.errors import OccDataError

__all__ = ["TABLE_NAMES", "iter_table_rows", "load_table", "usable_as_file_name"]

TABLE_NAMES: tuple[str, ...] = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)

_CHUNK = 1 << 20
_WS = " \t\r\n"


class _Scanner:
    """A bounded window `buf[pos:]` over a text file, refilled in `_CHUNK`s; offsets for errors."""

    def __init__(self, fh: Any, path: Path) -> None:
        self.fh, self.path = fh, path
        self.buf = fh.read(_CHUNK)
        self.eof = len(self.buf) < _CHUNK
        self.pos = 0
        self.consumed = 0  # characters dropped from the front of buf

    def fill(self) -> bool:
        """Append the next chunk (dropping what was consumed); False at the end of the file."""
        if self.eof:
            return False
        more = self.fh.read(_CHUNK)
        self.eof = len(more) < _CHUNK
        self.consumed += self.pos
        self.buf = self.buf[self.pos:] + more
        self.pos = 0
        return bool(more)

    def peek(self) -> str:
        """The next non-blank character ("" at the end of the file), not consumed."""
        while True:
            while self.pos < len(self.buf) and self.buf[self.pos] in _WS:
                self.pos += 1
            if self.pos < len(self.buf) or not self.fill():
                return self.buf[self.pos] if self.pos < len(self.buf) else ""

    def decode(self, decoder: json.JSONDecoder) -> tuple[Any, int]:
        """The JSON value at the cursor and where it ends, reading more of the file until it is complete."""
        while True:
            try:
                return decoder.raw_decode(self.buf, self.pos)
            except json.JSONDecodeError as exc:
                if not self.fill():
                    raise self.fail(exc.msg) from None

    def fail(self, why: str) -> OccDataError:
        return OccDataError(f"malformed JSON in {self.path}: {why} at character {self.consumed + self.pos}")


def _rows(sc: _Scanner) -> Iterator[dict[str, Any]]:
    """The objects of the JSON array at the cursor, one at a time."""
    decoder = json.JSONDecoder()
    if sc.peek() != "[":
        raise sc.fail("expected a JSON array of rows")
    sc.pos += 1
    first = True
    while True:
        ch = sc.peek()
        if ch == "]":
            sc.pos += 1
            if sc.peek():
                raise sc.fail("extra data after the array")
            return
        if not first:
            if ch != ",":
                raise sc.fail("unexpected end of file" if not ch else "expected ',' or ']' between rows")
            sc.pos += 1
            ch = sc.peek()
        if not ch:
            raise sc.fail("unexpected end of file")
        row, end = sc.decode(decoder)
        if not isinstance(row, dict):
            raise sc.fail("a row is not a JSON object")
        sc.pos = end
        first = False
        yield row


def iter_table_rows(path: Path) -> Iterator[dict[str, Any]]:
    """Yield the rows (dicts) of one table file: a JSON array of objects, decoded incrementally.

    Raises `OccDataError` naming the file for a missing file, malformed JSON, a top level that is
    not an array, or a row that is not an object.
    """
    path = Path(path)
    if not path.is_file():
        raise OccDataError(f"missing table: {path}")
    try:
        fh = open(path, encoding="utf-8")  # noqa: SIM115 - closed in finally
    except OSError as exc:
        raise OccDataError(f"cannot read table {path}: {exc.strerror}") from None
    try:
        yield from _rows(_Scanner(fh, path))
    except UnicodeDecodeError:
        raise OccDataError(f"malformed JSON in {path}: not UTF-8 text") from None
    finally:
        fh.close()


def load_table(
    path: Path,
    keep: Callable[[dict[str, Any]], bool] | None = None,
    warn: Callable[[str], None] | None = None,
) -> dict[str, dict[str, Any]]:
    """Rows of a table keyed by `token`, optionally filtered by `keep(row)`.

    Tokens must be usable as file names (`usable_as_file_name`): the Occ3D layout and the
    prediction writer use them as folder names. A token that appears twice among the
    kept rows with different content is an error naming the table and the token (otherwise the
    last row would silently win); identical duplicates are kept once and reported through `warn`
    (one message per table).
    """
    out: dict[str, dict[str, Any]] = {}
    identical: list[str] = []
    for row in iter_table_rows(path):
        if keep is not None and not keep(row):
            continue
        token = row.get("token")
        if not isinstance(token, str):
            raise OccDataError(f"malformed table {path}: a row has no string 'token' field")
        if not usable_as_file_name(token):
            raise OccDataError(
                f"malformed table {path}: token {token!r} is empty or not usable as a file name "
                "(tokens name folders of label and prediction files: no '/', '\\', NUL, '.' or '..')"
            )
        seen = out.get(token)
        if seen is not None:
            if seen != row:
                raise OccDataError(
                    f"duplicate token in {path.name}: {token!r} appears twice with different content "
                    f"(fields {_differing(seen, row)} differ); remove one of the rows"
                )
            identical.append(token)
            continue
        out[token] = row
    if identical and warn is not None:
        warn(
            f"{path.name}: {len(identical)} identical duplicate row(s) ignored (first token {identical[0]!r})"
        )
    return out


def usable_as_file_name(name: str) -> bool:
    """True if `name` can be one path component as is: non-empty, no '/', '\\' or NUL, not '.'/'..'."""
    return bool(name) and not any(ch in name for ch in "/\\\0") and name not in (".", "..")


def _differing(a: dict[str, Any], b: dict[str, Any]) -> str:
    keys = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
    return ", ".join(repr(k) for k in keys[:4]) + (", ..." if len(keys) > 4 else "")
