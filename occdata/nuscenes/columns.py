"""Kept table rows as columns: a few hundred bytes per row instead of a dict's few kilobytes.

A million keyframes keep ~15 M rows of sample_data and ego_pose. As Python dicts (keys, strings,
float lists) they took ~11 KiB per keyframe; here a row is its strings' UTF-8 bytes in one buffer,
its numbers in typed arrays, and a token's 8-byte hash in a sorted index. `ColumnTable` is a
read-only `Mapping` token -> row dict: a row is made again, equal to the one in the file, when it is
looked up, and dropped by the caller.

The columns' schema is the first row's: its keys and, per key, the kind of its value (a string, a
boolean, a number, a list of numbers of that length). A row that does not fit (other keys, a value of
another kind, an integer beyond float64's exact range, a string that is not valid Unicode) is kept
whole as a dict: correct for any table, compact for the regular ones.
"""

from __future__ import annotations

import bisect
import enum
import mmap
import tempfile
import weakref
from array import array
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

__all__ = ["ColumnTable", "HashIndex", "TableBuilder", "TextColumn"]

_RELEASE_EVERY = 1 << 16  # rows between two `ColumnTable.release` in a pass over every row (`positions`)
_EXACT = 2**53  # integers up to this are exact in float64
_NO = object()  # `prepare`: the value does not fit the column


class _Kind(enum.Enum):
    TEXT = "text"
    BOOL = "bool"
    NUMBER = "number"  # int or float: float64 plus a flag saying it was an int
    NUMBERS = "numbers"  # a list of numbers of one length: float64 each, read back as floats


def _kind_of(value: Any) -> tuple[_Kind, int] | None:
    if type(value) is str:
        return _Kind.TEXT, 0
    if type(value) is bool:
        return _Kind.BOOL, 0
    if type(value) in (int, float):
        return _Kind.NUMBER, 0
    if type(value) is list and value and all(type(v) in (int, float) for v in value):
        return _Kind.NUMBERS, len(value)
    return None


class _Paged:
    """An append-only typed buffer (an `array` of `typecode`, `+=` for bytes) kept in an unnamed temporary
    file: appended values wait in a tail written out each `_FLUSH` bytes. `seal()` gives what a finished
    table reads, a memoryview indexed like the array: the file mapped read-only (or, under `_FLUSH`
    bytes, the tail itself). The mapped pages are the page cache's, not this process's heap: reading
    maps them in, `ColumnTable.release()` maps them out again."""

    _FLUSH = 1 << 20

    def __init__(self, typecode: str) -> None:
        self.typecode = typecode
        self.tail = array(typecode)
        self._written = 0
        self._file: Any = None

    def __len__(self) -> int:
        return self._written + len(self.tail)

    def append(self, value: Any) -> None:
        self.tail.append(value)
        self._write_if_full()

    def extend(self, values: Any) -> None:
        self.tail.extend(values)
        self._write_if_full()

    def __iadd__(self, data: bytes) -> _Paged:
        self.tail.frombytes(data)
        self._write_if_full()
        return self

    def _write_if_full(self) -> None:
        if len(self.tail) * self.tail.itemsize >= self._FLUSH:
            self._write()

    def _write(self) -> None:
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="occdata-table-")  # already unlinked
            weakref.finalize(self, self._file.close)  # a table abandoned half read closes its files too
        self._file.write(self.tail)
        self._written += len(self.tail)
        self.tail = array(self.typecode)

    def seal(self) -> tuple[memoryview, mmap.mmap | None]:
        """The values as a read-only memoryview, and the mapping behind it (None: kept in memory)."""
        if self._file is None:
            return memoryview(self.tail).toreadonly(), None
        self._write()
        self._file.flush()
        mapped = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        self._file.close()  # the mapping keeps the data
        self._file = None
        return memoryview(mapped).cast(self.typecode), mapped


def _store(typecode: str, paged: bool) -> Any:
    """A column's buffer: in memory (`array`, or `bytearray` for "B") or `_Paged`."""
    if paged:
        return _Paged(typecode)
    return bytearray() if typecode == "B" else array(typecode)


class TextColumn:
    """Strings as UTF-8 bytes in one buffer with end offsets: `append(s)`, `get(i)`, `len` (`paged`: the
    buffers in a temporary file, `_Paged`)."""

    def __init__(self, paged: bool = False) -> None:
        self.buf = _store("B", paged)
        self.ends = _store("Q", paged)

    def prepare(self, value: Any) -> Any:
        """What `push` stores for `value`, or `_NO` if it does not fit."""
        if type(value) is not str:
            return _NO
        try:
            return value.encode("utf-8")
        except UnicodeEncodeError:  # a lone surrogate (JSON "\ud800"): kept in the dict
            return _NO

    def push(self, encoded: bytes) -> None:
        self.buf += encoded
        self.ends.append(len(self.buf))

    def append(self, value: str) -> None:
        self.push(value.encode("utf-8"))

    def __len__(self) -> int:
        return len(self.ends)

    def get(self, i: int) -> str:
        start = self.ends[i - 1] if i else 0
        return str(self.buf[start:self.ends[i]], "utf-8")


class _Tokens:
    """Lowercase hexadecimal tokens of one even length (nuScenes' 32 digits, Lyft's 64), or "": 16
    bytes a nuScenes token and a flag, not 32 bytes of text and an 8-byte offset."""

    def __init__(self, paged: bool = False) -> None:
        self.width = 0  # bytes a token, set by the first one
        self.buf = _store("B", paged)
        self.empty = _store("b", paged)

    def prepare(self, value: Any) -> Any:
        if type(value) is not str:
            return _NO
        if not value:
            return b""
        if len(value) % 2 or (self.width and len(value) != 2 * self.width):
            return _NO
        try:
            raw = bytes.fromhex(value)
        except ValueError:
            return _NO
        return raw if raw.hex() == value else _NO  # uppercase would not read back the same

    def push(self, raw: bytes) -> None:
        if raw and not self.width:
            self.width = len(raw)
            self.buf += bytes(self.width * len(self.empty))  # the empty ones so far
        self.empty.append(not raw)
        self.buf += raw or bytes(self.width)

    def get(self, i: int) -> str:
        return "" if self.empty[i] else self.buf[i * self.width:(i + 1) * self.width].hex()


def _is_token(value: str) -> bool:
    return not value or (len(value) % 2 == 0 and all(c in "0123456789abcdef" for c in value))


class _Bool:
    def __init__(self, paged: bool = False) -> None:
        self.values = _store("b", paged)

    def prepare(self, value: Any) -> Any:
        return value if type(value) is bool else _NO

    def push(self, value: bool) -> None:
        self.values.append(value)

    def get(self, i: int) -> bool:
        return bool(self.values[i])


class _Number:
    def __init__(self, paged: bool = False) -> None:
        self.values = _store("d", paged)
        self.is_int = _store("b", paged)

    def prepare(self, value: Any) -> Any:
        return value if type(value) is float or (type(value) is int and -_EXACT <= value <= _EXACT) else _NO

    def push(self, value: float) -> None:
        self.values.append(value)
        self.is_int.append(type(value) is int)

    def get(self, i: int) -> int | float:
        v = self.values[i]
        return int(v) if self.is_int[i] else v


class _Numbers:
    def __init__(self, length: int, paged: bool = False) -> None:
        self.length = length
        self.values = _store("d", paged)

    def prepare(self, value: Any) -> Any:
        if type(value) is not list or len(value) != self.length:
            return _NO
        for v in value:
            if not (type(v) is float or (type(v) is int and -_EXACT <= v <= _EXACT)):
                return _NO
        return value

    def push(self, value: list[float]) -> None:
        self.values.extend([float(v) for v in value])

    def get(self, i: int) -> list[float]:
        return self.values[i * self.length:(i + 1) * self.length].tolist()


def _column(kind: tuple[_Kind, int], value: Any, paged: bool) -> Any:
    if kind[0] is _Kind.NUMBERS:
        return _Numbers(kind[1], paged)
    if kind[0] is _Kind.TEXT:
        return _Tokens(paged) if _is_token(value) else TextColumn(paged)
    return _Bool(paged) if kind[0] is _Kind.BOOL else _Number(paged)


def _seal(col: Any) -> list[mmap.mmap]:
    """Turn a column's `_Paged` buffers into read-only views; the mappings made."""
    maps = []
    for name, value in vars(col).items():
        if isinstance(value, _Paged):
            view, mapped = value.seal()
            setattr(col, name, view)
            if mapped is not None:
                maps.append(mapped)
    return maps


class TableBuilder:
    """Rows appended in file order (`append`), then `finish()` -> `ColumnTable`. `paged`: the columns
    are written to temporary files as they grow and mapped read-only when finished (`_Paged`); the
    table's index (16 bytes a row) and per-row slots and hashes (8 each) stay in memory."""

    def __init__(self, paged: bool = False) -> None:
        self._paged = paged
        self._keys: tuple[str, ...] | None = None
        self._cols: list[Any] = []
        self._slots = array("q")  # per row: >= 0 a column row, < 0 `-1 - k`, the k-th dict row
        self._n_col = 0
        self._odd: list[dict[str, Any]] = []
        self._hashes = array("q")

    def append(self, token: str, row: dict[str, Any]) -> None:
        if self._keys is None:
            self._start(row)
        self._hashes.append(hash(token))
        values = self._prepare(row)
        if values is None:
            self._slots.append(-1 - len(self._odd))
            self._odd.append(row)
            return
        for col, value in zip(self._cols, values, strict=True):
            col.push(value)
        self._slots.append(self._n_col)
        self._n_col += 1

    def _start(self, row: dict[str, Any]) -> None:
        kinds = {k: _kind_of(v) for k, v in row.items()}
        self._keys = tuple(k for k, kind in kinds.items() if kind is not None)
        if len(self._keys) != len(row):
            self._keys = ()  # a value of no known kind: every row is kept whole
        self._cols = [_column(kinds[k], row[k], self._paged) for k in self._keys]  # type: ignore[arg-type]

    def _prepare(self, row: dict[str, Any]) -> list[Any] | None:
        """Each column's value of `row`, ready to push; None if the row does not fit the columns."""
        if not self._keys or len(row) != len(self._keys):
            return None
        out = []
        for key, col in zip(self._keys, self._cols, strict=True):
            value = col.prepare(row.get(key, _NO))
            if value is _NO:
                return None
            out.append(value)
        return out

    def finish(self) -> ColumnTable:
        maps = [m for col in self._cols for m in _seal(col)]
        return ColumnTable(self._keys or (), self._cols, self._slots, self._odd, self._hashes, maps)


def _held(buffer: Any) -> int:
    """Bytes of a column buffer held in memory (a mapped one: none)."""
    if isinstance(buffer, (array, bytearray)):
        return len(buffer) * (buffer.itemsize if isinstance(buffer, array) else 1)
    if isinstance(buffer, memoryview) and not isinstance(buffer.obj, mmap.mmap):
        return buffer.nbytes
    return 0


def _view(a: array) -> np.ndarray:
    """An int64 array('q') seen as numpy, without a copy."""
    return np.frombuffer(a, dtype=np.int64) if len(a) else np.zeros(0, np.int64)


class HashIndex:
    """Positions by `hash(key)` (16 bytes an entry, not a dict entry's ~100): `candidates(key)` yields
    the positions whose hash is key's, in position order, and callers compare the key itself (two keys
    may share a 64-bit hash); `first(hashes)` the first such position of many hashes at once (-1: none).
    Str hashes differ between processes: an index is made again where it is used, never sent."""

    def __init__(self, hashes: np.ndarray) -> None:
        order = np.argsort(hashes, kind="stable")
        # kept as arrays (`bisect` on them is several times faster than numpy for one key), seen as numpy
        self._sorted_a, self._order_a = array("q", hashes[order].tobytes()), array("q", order.tobytes())
        self._sorted, self._order = _view(self._sorted_a), _view(self._order_a)

    def candidates(self, key: Any) -> Iterator[int]:
        h = hash(key)
        keys = self._sorted_a
        i = bisect.bisect_left(keys, h)
        while i < len(keys) and keys[i] == h:
            yield self._order_a[i]
            i += 1

    def first(self, hashes: np.ndarray) -> np.ndarray:
        if not len(self._sorted):
            return np.full(len(hashes), -1, np.int64)
        i = np.minimum(np.searchsorted(self._sorted, hashes), len(self._sorted) - 1)
        return np.where(self._sorted[i] == hashes, self._order[i], -1)

    @property
    def nbytes(self) -> int:
        return self._sorted.nbytes + self._order.nbytes


class ColumnTable(Mapping[str, dict[str, Any]]):
    """Rows keyed by token, in file order; each lookup makes the row dict again (equal to the file's:
    numbers keep their int/float type except inside lists, which read back as floats).

    `len` rows; `rows()` yields `(position, row)`; `position(token)` the row's place in file
    order (-1 if absent); `positions_of_hashes(h)` the same for many `hash(token)` values at once."""

    def __init__(self, keys: tuple[str, ...], cols: list[Any], slots: array, odd: list[dict[str, Any]],
                 hashes: array, maps: list[mmap.mmap] | None = None) -> None:
        self._keys, self._cols, self._odd = keys, cols, odd
        self._maps = maps or []  # the paged columns' mappings (`release`)
        self._slots_a = slots  # indexed one row at a time (a Python int, no numpy scalar)
        self._slots = _view(slots)
        self._col_of = dict(zip(keys, cols, strict=True))
        self._hashes = _view(hashes)
        self._index = HashIndex(self._hashes)

    def __len__(self) -> int:
        return len(self._slots)

    def row_at(self, pos: int) -> dict[str, Any]:
        """The row at file position `pos` (a new dict; a row kept whole is the kept dict itself)."""
        slot = self._slots_a[pos]
        if slot < 0:
            return self._odd[-1 - slot]
        return {key: col.get(slot) for key, col in self._col_of.items()}

    def value_at(self, pos: int, key: str) -> Any:
        """One field of the row at `pos` (KeyError if the row has no such field)."""
        slot = self._slots_a[pos]
        if slot < 0:
            return self._odd[-1 - slot][key]
        return self._col_of[key].get(slot)

    def get_at(self, pos: int, key: str, default: Any = None) -> Any:
        """`value_at`, or `default` where the row has no such field."""
        try:
            return self.value_at(pos, key)
        except KeyError:
            return default

    def position(self, token: Any) -> int:
        if type(token) is not str:
            return -1
        return next((pos for pos in self._index.candidates(token) if self.value_at(pos, "token") == token), -1)

    def positions_of_hashes(self, hashes: np.ndarray) -> np.ndarray:
        """`(k,) int64` file positions of the rows whose token hashes are `hashes` `(k,) int64`, -1 where
        none (a 64-bit hash collision would give a wrong row; callers that must be exact compare)."""
        return self._index.first(hashes)

    def token_hashes(self) -> np.ndarray:
        """`(len,) int64` `hash(token)` of each row in file order (read-only)."""
        return self._hashes

    def hashes_of(self, key: str) -> np.ndarray:
        """`(len,) int64` `hash(row[key])` of each row, in file order (`hash(None)` where the row has no such
        field)."""
        return np.fromiter((hash(self._value_or_none(p, key)) for p in self.positions()), np.int64, len(self))

    def _value_or_none(self, pos: int, key: str) -> Any:
        value = self.get_at(pos, key)
        return value if isinstance(value, (str, int, float, bool)) or value is None else repr(value)

    def __getitem__(self, token: str) -> dict[str, Any]:
        pos = self.position(token)
        if pos < 0:
            raise KeyError(token)
        return self.row_at(pos)

    def __contains__(self, token: object) -> bool:
        return self.position(token) >= 0

    def __iter__(self) -> Iterator[str]:
        for pos in self.positions():
            yield self.value_at(pos, "token")

    def rows(self) -> Iterator[tuple[int, dict[str, Any]]]:
        """`(position, row)` in file order, each row a new dict."""
        for pos in self.positions():
            yield pos, self.row_at(pos)

    def without(self, keys: tuple[str, ...]) -> ColumnTable:
        """The same rows without the columns `keys` (their values were taken elsewhere); rows kept whole
        keep every field."""
        out = object.__new__(ColumnTable)
        vars(out).update(vars(self))
        kept = [(k, c) for k, c in zip(self._keys, self._cols, strict=True) if k not in keys]
        out._keys, out._cols = tuple(k for k, _ in kept), [c for _, c in kept]
        out._col_of = dict(kept)
        return out

    def positions(self) -> Iterator[int]:
        """0, 1, ..., len - 1, the paged columns' pages mapped out after each `_RELEASE_EVERY` rows: a
        pass over every row holds a bounded part of the table in this process."""
        n = len(self)
        for p0 in range(0, n, _RELEASE_EVERY):
            yield from range(p0, min(p0 + _RELEASE_EVERY, n))
            self.release()

    def release(self) -> None:
        """Map out the paged columns' pages read so far (they stay in the page cache, and are mapped in
        again when read): what the table holds in this process then is its index, slots and hashes."""
        for mapped in self._maps:
            mapped.madvise(mmap.MADV_DONTNEED)

    def __reduce__(self) -> tuple[Any, ...]:
        raise TypeError("a ColumnTable is indexed by this process's str hashes and is not sent to other processes")

    def nbytes(self) -> int:
        """Bytes held in columns and indexes (not counting the rows kept whole)."""
        cols = sum(_held(a) for c in self._cols for a in vars(c).values())
        return cols + self._slots.nbytes + self._index.nbytes + self._hashes.nbytes
