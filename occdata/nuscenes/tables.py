"""Streaming reader for nuScenes JSON tables.

The trainval `sample_data.json` and `ego_pose.json` hold millions of rows; parsing them whole costs
several GB. Rows are decoded one at a time from a bounded buffer and filtered on the fly, so memory
stays proportional to the rows kept.
"""

from __future__ import annotations

import json
import sys
from array import array
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from occdata.errors import OccDataError
from occdata.nuscenes.columns import ColumnTable, TableBuilder
from occdata.nuscenes.spill import BUCKETS, BucketSpill, bucket_of

__all__ = ["TABLE_NAMES", "TokenSet", "iter_table_rows", "load_table", "usable_as_file_name"]

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
_MAX_ROW = 64 << 20  # characters: nuScenes rows are under a kilobyte; a longer one is a broken file
_CUT = 16  # a decoding error this close to the window's end may be a value cut by it (`true`, `1e5`, `\u00e9`)
_SHARED_MAX = 64  # characters: tokens (32 in nuScenes, 64 in Lyft) and names, not file paths
_WS = " \t\r\n"


class _Scanner:
    """A bounded window `buf[pos:]` over a text file, refilled in `_CHUNK`s; offsets for errors.

    A row cut by the window's end is completed by refills that double the window (linear in the row's
    length); a decoding error inside the window is a malformed row at once, never a reason to read on:
    each retry re-decodes the row, so refilling a chunk at a time read the whole rest of the file
    and copied it once per chunk (quadratic) before a bad row's error."""

    def __init__(self, fh: Any, path: Path) -> None:
        self.fh, self.path = fh, path
        self.buf = fh.read(_CHUNK)
        self.eof = len(self.buf) < _CHUNK
        self.pos = 0
        self.consumed = 0  # characters dropped from the front of buf

    def fill(self) -> bool:
        """Append at least a chunk, at most as much as is left unconsumed (dropping what was consumed);
        False at the end of the file."""
        if self.eof:
            return False
        want = max(_CHUNK, len(self.buf) - self.pos)
        more = self.fh.read(want)
        self.eof = len(more) < want
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
                cut = exc.pos >= len(self.buf) - _CUT or exc.msg.startswith("Unterminated string")
                if not cut:
                    self.pos = exc.pos
                    raise self.fail(exc.msg) from None
                if len(self.buf) - self.pos > _MAX_ROW:
                    raise self.fail(f"a row longer than {_MAX_ROW >> 20} M characters") from None
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


_SET_IN_MEMORY = 1 << 18  # hashes a TokenSet holds before it writes them to disk (2 MiB)
_HASH = np.dtype([("h", "<i8")])


class TokenSet:
    """Every token of a table as 8-byte hashes: which tokens exist, for checking the references of the
    rows kept, and which repeat. Hashes are Python's, valid in this process only; a false "exists"
    needs a 64-bit collision.

    Up to `in_memory` hashes (default 2**18) stay in memory. Past that they go to an unnamed temporary
    file in 64 buckets by their top bits (`BucketSpill`), and a query reads one bucket at a time: the
    memory held stays ~2 MiB and a query's 1/64 of the table, however large the table (nuScenes'
    sample_data and ego_pose have ~77 rows a keyframe; a million keyframes, 77 M tokens: 616 MB of
    hashes, ~1.8 GB while `repeated` sorted them in memory)."""

    def __init__(self, in_memory: int | None = None) -> None:
        self._buf = array("q")
        self._in_memory = _SET_IN_MEMORY if in_memory is None else in_memory
        self._sorted: np.ndarray | None = None
        self._spilled: BucketSpill | None = None

    def add(self, token: str) -> None:
        self._buf.append(hash(token))
        self._sorted = None
        if len(self._buf) >= self._in_memory:
            self._write()

    def _write(self) -> None:
        """The hashes in memory to their buckets on disk."""
        if self._spilled is None:
            self._spilled = BucketSpill(_HASH, "h", in_memory=1)  # each `add` written at once
        if len(self._buf):
            self._spilled.add(np.frombuffer(self._buf, dtype=np.int64).view(_HASH))
            self._buf = array("q")

    def _raw(self, k: int) -> np.ndarray:
        """`(n,) int64` bucket k's hashes as added, repeats included (the whole set when it never
        spilled: `k` ignored)."""
        if self._spilled is None:
            return np.frombuffer(self._buf, dtype=np.int64)
        self._write()
        return self._spilled.bucket(k)["h"]

    def _present(self, k: int) -> np.ndarray:
        """`(n,) int64` bucket k's distinct hashes, sorted (the whole set's, made once, when it never
        spilled)."""
        if self._spilled is None:
            if self._sorted is None:
                self._sorted = np.unique(self._raw(-1))
            return self._sorted
        return np.unique(self._raw(k))

    def __contains__(self, token: object) -> bool:
        return bool(self.has_hashes(np.array([hash(token)], dtype=np.int64))[0])

    def repeated(self) -> set[int]:
        """The hashes added more than once (a token that repeats, or a 64-bit collision)."""
        out: set[int] = set()
        for k in range(BUCKETS if self._spilled is not None else 1):
            raw = self._raw(k)
            if len(raw) > 1:
                values, counts = np.unique(raw, return_counts=True)
                out.update(int(v) for v in values[counts > 1])
        return out

    def has_hashes(self, hashes: np.ndarray) -> np.ndarray:
        """`(k,) bool`: which of the `hash(token)` values `hashes` `(k,) int64` are in the set (a spilled
        set reads the buckets the queries fall in, one at a time)."""
        hashes = np.asarray(hashes, dtype=np.int64)
        if self._spilled is None:
            return np.isin(hashes, self._present(-1))
        out = np.zeros(len(hashes), dtype=bool)
        which = bucket_of(hashes)
        for k in np.unique(which).tolist():
            mask = which == k
            out[mask] = np.isin(hashes[mask], self._present(int(k)))
        return out

    def hits(self, tokens: list[str]) -> list[str]:
        """The `tokens` that are in the set."""
        if not tokens:
            return []
        mask = self.has_hashes(np.fromiter((hash(t) for t in tokens), np.int64, len(tokens)))
        return [t for t, m in zip(tokens, mask, strict=True) if m]


def load_table(
    path: Path,
    keep: Callable[[dict[str, Any]], bool] | None = None,
    warn: Callable[[str], None] | None = None,
    tokens: TokenSet | None = None,
    columns: bool = False,
) -> dict[str, dict[str, Any]] | ColumnTable:
    """Rows of a table keyed by `token`, optionally filtered by `keep(row)`; `tokens` (if given)
    receives the token of every row, kept or not.

    Tokens must be usable as file names (`usable_as_file_name`): the Occ3D layout and the
    prediction writer use them as folder names. A token that appears twice with different content
    is an error naming the table and the token (otherwise the last row would silently win), whether
    `keep` keeps both copies, one or none: every command refuses the same tree. Repeated tokens are
    found through the hashes of all tokens and compared in a second read of the file, which only
    happens when a token repeats. Identical duplicates are kept once and reported through `warn`
    (one message per table). With `columns`, the rows are kept as a `ColumnTable` (a few hundred bytes
    a row, not a dict's kilobytes: for sample_data and ego_pose, which grow with the dataset).
    """
    if columns:
        return _load_columns(path, keep, warn, tokens)
    out: dict[str, dict[str, Any]] = {}
    every = tokens if tokens is not None else TokenSet()
    for token, row in _kept_rows(path, keep, every):
        seen = out.get(token)
        if seen is not None and seen != row:
            raise _duplicate(path, token, seen, row)
        if seen is None:
            out[token] = _shared_strings(row)
    identical = _compare_repeated(path, every.repeated())
    if identical and warn is not None:
        warn(f"{path.name}: {len(identical)} identical duplicate row(s) ignored (first token {identical[0]!r})")
    return out


def _kept_rows(path: Path, keep: Callable[[dict[str, Any]], bool] | None,
               every: TokenSet) -> Iterator[tuple[str, dict[str, Any]]]:
    """`(token, row)` of each row `keep` keeps, its token checked; `every` gets every row's token."""
    for row in iter_table_rows(path):
        token = row.get("token")
        if isinstance(token, str):
            every.add(token)
        if keep is None or keep(row):
            yield _checked_token(path, row), row


def _checked_token(path: Path, row: dict[str, Any]) -> str:
    token = row.get("token")
    if not isinstance(token, str):
        raise OccDataError(f"malformed table {path}: a row has no string 'token' field")
    if not usable_as_file_name(token):
        raise OccDataError(
            f"malformed table {path}: token {token!r} is empty or not usable as a file name "
            "(tokens name folders of label and prediction files: no '/', '\\', NUL, '.' or '..')"
        )
    return token


def _load_columns(path: Path, keep: Callable[[dict[str, Any]], bool] | None, warn: Callable[[str], None] | None,
                  tokens: TokenSet | None) -> ColumnTable:
    """`load_table` into a `ColumnTable`: the same checks, duplicates found by the tokens' hashes."""
    builder = TableBuilder(paged=True)  # the columns in temporary files: memory keeps ~32 bytes a row
    every = tokens if tokens is not None else TokenSet()
    for token, row in _kept_rows(path, keep, every):
        builder.append(token, row)
    table = builder.finish()
    identical = _compare_repeated(path, every.repeated())  # differing copies raise here
    if identical:
        table = _first_copies(table)
        if warn is not None:
            warn(f"{path.name}: {len(identical)} identical duplicate row(s) ignored (first token {identical[0]!r})")
    return table


def _first_copies(table: ColumnTable) -> ColumnTable:
    """`table` without the later copies of a repeated token (identical rows: checked by the caller)."""
    seen: set[str] = set()
    builder = TableBuilder(paged=True)
    for _, row in table.rows():
        if row["token"] not in seen:
            seen.add(row["token"])
            builder.append(row["token"], row)
    return builder.finish()


def _shared_strings(row: dict[str, Any]) -> dict[str, Any]:
    """`row` with its keys and short string values (tokens, channels, formats) interned. The JSON
    decoder makes new strings for every row (its key memo lives for one `raw_decode`), so a kept
    row's 10-12 keys and the tokens it repeats (`sample_token`, `prev`, `next`, `ego_pose_token`,
    `calibrated_sensor_token`) were ~60-80 bytes each, per row: about half of the tables' memory."""
    return {sys.intern(k): sys.intern(v) if type(v) is str and len(v) <= _SHARED_MAX else v for k, v in row.items()}


def _duplicate(path: Path, token: str, a: dict[str, Any], b: dict[str, Any]) -> OccDataError:
    return OccDataError(f"duplicate token in {path.name}: {token!r} appears twice with different content "
                        f"(fields {_differing(a, b)} differ); remove one of the rows")


def _compare_repeated(path: Path, repeated: set[int]) -> list[str]:
    """Read the file again for the rows whose token hash repeats: copies that differ are an error;
    returns the tokens of the identical extra copies, in file order."""
    if not repeated:
        return []
    first: dict[str, dict[str, Any]] = {}
    identical: list[str] = []
    for row in iter_table_rows(path):
        token = row.get("token")
        if not isinstance(token, str) or hash(token) not in repeated:
            continue
        seen = first.setdefault(token, row)
        if seen is not row:
            if seen != row:
                raise _duplicate(path, token, seen, row)
            identical.append(token)
    return identical


def usable_as_file_name(name: str) -> bool:
    """True if `name` can be one path component as is: non-empty, no '/', '\\' or NUL, not '.'/'..'."""
    return bool(name) and not any(ch in name for ch in "/\\\0") and name not in (".", "..")


def _differing(a: dict[str, Any], b: dict[str, Any]) -> str:
    keys = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
    return ", ".join(repr(k) for k in keys[:4]) + (", ..." if len(keys) > 4 else "")
