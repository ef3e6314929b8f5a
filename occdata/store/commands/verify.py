"""`occdata verify`: every committed sample's chunks present and its checksums recomputed.

The client lists each array's chunks once and plans: `VerifyJob` tasks of whole blocks, each given
the absent chunks it may meet (normally none: a few integers). Everything per sample runs in the
tasks, block by block (`verify_rows`): the absent-chunk judgement, the flat arrays' ranges against
their absent chunks, and the checksums, which read every byte of the store. Tasks run on
`occdata.runtime.cluster.run_tasks`: in this process (`client` None) or on Dask workers, as the
build's blocks do. A task opens the store itself (once per process and run) and reads only its own
rows, so nothing of the store's size travels; its problems come back and are put in sample order,
so the report is the same for any number of workers.
"""

from __future__ import annotations

import uuid
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from occdata.errors import OccDataError
from occdata.runtime.cluster import run_tasks
from occdata.runtime.tasks import StopCheck
from occdata.store.integrity import StoreIntegrity
from occdata.store.layout import (
    FLAT_ARRAYS,
    FLAT_OF_OFFSETS,
    STATE_PENDING,
    camera_count,
    checksummed_names,
    grid_shape,
    has_flow,
    per_sample,
    token_str,
)
from occdata.store.reader import StoreReader

__all__ = ["OpenStore", "Problem", "VerifyJob", "first_absent_chunk", "pending_samples", "verify_rows",
           "verify_store"]

TASK_SAMPLES = 256  # samples per task at most: a few hundred MB read, ~1-5 s on one core; blocks of 32 inside
MERGE_GAP = 4  # flat ranges closer than this many chunks are read as one request


@dataclass(frozen=True)
class Problem:
    index: int
    token: str
    array: str
    reason: str


Absent = tuple[tuple[str, tuple[int, ...]], ...]  # (array, its absent chunk indices along the row axis)


@dataclass(frozen=True)
class VerifyJob:
    """Samples [`i0`, `i1`) of the store at `store` (a path or URL), checked `block` samples at a
    time: one task (picklable, small). `absent`: the chunks of each array that the client's listing
    lacks, as far as these samples can meet them. `run`: the verify run (a process opens the store
    once per run)."""

    store: str
    i0: int
    i1: int
    block: int = 32
    absent: Absent = ()
    run_id: str = ""

    def __post_init__(self) -> None:
        if not 0 <= self.i0 <= self.i1 or self.block < 1:
            raise OccDataError(f"verify task [{self.i0}, {self.i1}) with blocks of {self.block}: not a sample range")

    @property
    def units(self) -> int:
        return self.i1 - self.i0

    def run(self, should_stop: StopCheck) -> tuple[Problem, ...]:
        store = _open(self.store, self.run_id)  # the layout checked again: a worker sees what the client saw
        absent = {name: np.asarray(ks, dtype=np.int64) for name, ks in self.absent}
        out: list[Problem] = []
        for b0 in range(self.i0, self.i1, self.block):
            should_stop()
            out += verify_rows(store, b0, min(b0 + self.block, self.i1), absent)
        return tuple(out)


class OpenStore:
    """One process's view of a store for a verify run: the group, its arrays opened once (a group
    lookup is a metadata read), the checksum columns and the integrity helpers."""

    def __init__(self, group: zarr.Group, integrity: StoreIntegrity) -> None:
        self.group = group
        self.integrity = integrity
        self.names = integrity.names  # checksum columns
        attrs = integrity.attrs
        self.per_sample = tuple(s.name for s in per_sample(has_flow(attrs), grid_shape(attrs), camera_count(attrs))
                                if s.name != "status/state")  # the arrays judged chunk by chunk
        self._arrays: dict[str, zarr.Array] = {}

    def __getitem__(self, name: str) -> zarr.Array:
        if name not in self._arrays:
            self._arrays[name] = self.group[name]
        return self._arrays[name]

    def token(self, i: int) -> str:
        """Sample `i`'s token, one row read (a task holds no token table); "?" where unreadable."""
        try:
            return token_str(np.asarray(self["sample/token"][i]))
        except Exception:  # noqa: BLE001 - the token array itself may be the corrupt one
            return "?"


_opened: dict[tuple[str, str], OpenStore] = {}  # this process's store of the current run only


def _open(store: str, run_id: str) -> OpenStore:
    """The store opened once per process and run (a later run never sees a stale view)."""
    if (store, run_id) not in _opened:
        reader = StoreReader(store)
        _opened.clear()
        _opened[(store, run_id)] = OpenStore(reader.group, reader.integrity)
    return _opened[(store, run_id)]


def verify_store(reader: StoreReader, block: int = 32, progress: Callable[[int], None] | None = None,
                 client: Any = None, task_samples: int = TASK_SAMPLES) -> list[Problem]:
    """Missing chunks, checksum mismatches and unreadable chunks, each with the sample it belongs to,
    in sample order (a listing that failed first, as sample -1). `client`: a `distributed.Client`
    that runs the tasks (None: this process); the result does not depend on it.

    Raises `OccDataError` when the commit flags are missing or unreadable, or the checksum table has
    the wrong columns (then no sample can be judged). Pending samples are not problems: see
    `pending_samples`.
    """
    state = reader.state  # checked: a missing state chunk in a complete store raises
    names = checksummed_names(reader.has_flow)
    columns = reader.group["status/checksum"].shape[1]
    if columns != len(names):
        raise OccDataError(f"{reader.path}: checksum table has {columns} columns, expected {len(names)}")
    # Whole blocks per task (a chunk is never read by two tasks), at most `task_samples`, and at least
    # ~16 tasks where the store has the blocks: two workers given two large tasks finish unevenly.
    spread = -(-reader.n_samples // (16 * block)) * block
    step = max(block, min(task_samples // block * block, spread))
    bounds = [(i0, min(i0 + step, reader.n_samples)) for i0 in range(0, reader.n_samples, step)]
    problems, absent = _plan_absent(reader, state, bounds)
    run_id = uuid.uuid4().hex
    jobs = [VerifyJob(str(reader.path), i0, i1, block, a, run_id) for (i0, i1), a in zip(bounds, absent, strict=True)]
    if client is None:  # this process: the reader's open store, no second open
        _opened.clear()
        _opened[(str(reader.path), run_id)] = OpenStore(reader.group, reader.integrity)
    found: dict[int, tuple[Problem, ...]] = {}

    def on_result(job: VerifyJob, result: tuple[Problem, ...]) -> None:
        found[job.i0] = result
        if progress:
            progress(job.units)

    try:
        run_tasks(client, jobs, desc="verify", unit="sample", progress=False, on_result=on_result)
    finally:
        _opened.clear()
    return problems + [p for i0 in sorted(found) for p in found[i0]]


def _plan_absent(reader: StoreReader, state: np.ndarray,
                 bounds: list[tuple[int, int]]) -> tuple[list[Problem], list[Absent]]:
    """Each array listed once: per task (`bounds`), the absent chunks its committed samples may meet.
    A listing that fails is a problem of sample -1 (that array's chunks are then not judged)."""
    problems: list[Problem] = []
    per_task: list[list[tuple[str, tuple[int, ...]]]] = [[] for _ in bounds]
    specs = per_sample(reader.has_flow, reader.grid_shape, reader.n_cams)
    for name in [s.name for s in specs if s.name != "status/state"] + list(FLAT_ARRAYS):
        try:
            ranges = _flat_chunk_ranges(reader, name, state, bounds) if name in FLAT_ARRAYS else None
            absent = np.flatnonzero(reader.integrity.absent_chunks(name)) if ranges is None else None
        except OccDataError as exc:
            problems.append(Problem(-1, "?", name, str(exc)))
            continue
        rows = reader.integrity.chunk_rows(name)
        for t, (i0, i1) in enumerate(bounds):
            if ranges is None:  # per-sample arrays: the task's own row chunks
                ks = absent[(absent >= i0 // rows) & (absent <= (i1 - 1) // rows)]
            else:
                ks = _absent_in(reader.integrity, name, *ranges[t])
            if len(ks):
                per_task[t].append((name, tuple(int(k) for k in ks)))
    return problems, [tuple(a) for a in per_task]


def _flat_chunk_ranges(reader: StoreReader, flat_name: str, state: np.ndarray,
                       bounds: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Per task, the chunk span [lo, hi) of its committed samples' non-empty ranges of a flat array
    ((0, 0): none), from the offsets table (small; read whole, vectorised)."""
    off_name = next(o for o, f in FLAT_OF_OFFSETS.items() if f == flat_name)
    off = reader.integrity.read_small(off_name)  # (n, cams, 2) int64: start, length
    rows = reader.integrity.chunk_rows(flat_name)
    n_chunks = -(-reader.group[flat_name].shape[0] // rows)
    start, length = off[..., 0], off[..., 1]
    used = (length > 0) & (state != STATE_PENDING)[:, None]
    lo = np.where(used, start // rows, np.iinfo(np.int64).max).min(axis=1)
    hi = np.where(used, (start + length - 1) // rows + 1, -1).max(axis=1)
    out = []
    for i0, i1 in bounds:
        a, b = int(lo[i0:i1].min(initial=np.iinfo(np.int64).max)), int(hi[i0:i1].max(initial=-1))
        a, b = max(a, 0), min(b, n_chunks)
        out.append((a, b) if a < b else (0, 0))
    return out


def _absent_in(integrity: StoreIntegrity, name: str, lo: int, hi: int) -> np.ndarray:
    """Chunk indices in [lo, hi) of `name` that the listing lacks."""
    if lo >= hi:
        return np.zeros(0, dtype=np.int64)
    present = integrity.present_chunks(name)
    have = present[np.searchsorted(present, lo):np.searchsorted(present, hi)]
    return np.setdiff1d(np.arange(lo, hi, dtype=np.int64), have, assume_unique=True)


def verify_rows(store: OpenStore, i0: int, i1: int, absent: Mapping[str, np.ndarray] | None = None) -> list[Problem]:
    """The problems of the committed samples in [`i0`, `i1`): absent chunks (`absent`: per array,
    the chunk indices the listing lacks) that hide a committed sample's data, and each checksummed
    array's rows and each sample's flat-array bytes recomputed against `status/checksum`. Reads only
    these rows (and their flat-array ranges). Sorted by sample, absent chunks first within one."""
    absent = absent or {}
    try:
        state = np.asarray(store["status/state"][i0:i1])
        stored = np.asarray(store["status/checksum"][i0:i1])
    except Exception as exc:  # noqa: BLE001 - a damaged chunk: this block cannot be judged, the others can
        return [Problem(i0, store.token(i0), "status/checksum", f"unreadable chunk ({exc})")]
    committed = state != STATE_PENDING
    if not committed.any():
        return []
    problems: list[Problem] = []
    for name in store.per_sample:
        if name in absent:
            problems += _absent_rows(store, name, i0, committed, stored, absent[name])
    offsets: dict[str, np.ndarray | None] = {}
    for off_name, flat_name in FLAT_OF_OFFSETS.items():
        try:
            offsets[off_name] = np.asarray(store[off_name][i0:i1])
        except Exception:  # noqa: BLE001 - reported per sample below
            offsets[off_name] = None
        if flat_name in absent and offsets[off_name] is not None:
            rows = store.integrity.chunk_rows(flat_name)
            first = first_absent_chunk(offsets[off_name], committed, rows, absent[flat_name])
            problems += [Problem(int(i0 + j), store.token(i0 + j), flat_name,
                                 f"chunk {store.integrity.chunk_file(flat_name, int(k) * rows)} is missing")
                         for j, k in enumerate(first) if k >= 0]
    idx = [int(i0 + j) for j in np.flatnonzero(committed)]
    for col, name in enumerate(store.names):
        if name not in FLAT_ARRAYS:
            problems += _check_array(store, name, i0, i1, idx, stored[:, col])
    for off_name, flat_name in FLAT_OF_OFFSETS.items():
        problems += _check_flat(store, off_name, flat_name, i0, idx, offsets[off_name],
                                stored[:, store.names.index(flat_name)])
    return sorted(problems, key=lambda p: p.index)


def _absent_rows(store: OpenStore, name: str, i0: int, committed: np.ndarray, stored: np.ndarray,
                 absent: np.ndarray) -> list[Problem]:
    """Committed rows of a per-sample array under an absent chunk that should not read as fill: all
    of them for `status/checksum` and unchecksummed arrays, else those whose checksum is not the
    fill row's."""
    rows = store.integrity.chunk_rows(name)
    hit = committed & np.isin((i0 + np.arange(len(committed))) // rows, absent)
    if name in store.names and name != "status/checksum":
        hit &= stored[:, store.names.index(name)] != store.integrity.fill_crc(name)
    rows_hit = [int(i0 + j) for j in np.flatnonzero(hit)]
    return [Problem(i, store.token(i), name, f"chunk {store.integrity.chunk_file(name, i)} is missing")
            for i in rows_hit]


def first_absent_chunk(offsets: np.ndarray, committed: np.ndarray, chunk_rows: int,
                       absent: np.ndarray) -> np.ndarray:
    """`(n,) int64`: per sample, the first absent chunk under its first camera range that meets one
    (cameras in order, chunks ascending), or -1. `offsets`: `(n, cams, 2) int64` (start, length) in
    elements of the flat array; `committed`: `(n,) bool`; `absent`: sorted chunk indices."""
    absent = np.sort(np.asarray(absent, dtype=np.int64))
    start, length = offsets[..., 0], offsets[..., 1]
    lo = start // chunk_rows
    hi = (start + np.maximum(length, 1) - 1) // chunk_rows  # inclusive
    a = np.searchsorted(absent, lo, side="left")
    hit = (length > 0) & committed[:, None] & (a < np.searchsorted(absent, hi, side="right"))
    first = np.where(hit, absent[np.minimum(a, max(len(absent) - 1, 0))] if len(absent) else -1, -1)
    cam = np.argmax(hit, axis=1)
    return np.where(hit.any(axis=1), first[np.arange(len(first)), cam], -1)


def _check_array(store: OpenStore, name: str, i0: int, i1: int, idx: list[int],
                 stored: np.ndarray) -> list[Problem]:
    """Rows of a per-sample array against their checksums (`stored`: rows i0..i1 of the column)."""
    problems: list[Problem] = []
    try:
        crcs = dict(zip(range(i0, i1), _crc_rows(store[name][i0:i1]), strict=True))
    except Exception:  # noqa: BLE001 - find the bad sample(s) one by one
        crcs = {}
        for i in idx:
            try:
                crcs[i] = _crc_rows(store[name][i : i + 1])[0]
            except Exception as exc:  # noqa: BLE001
                problems.append(Problem(i, store.token(i), name, f"unreadable chunk ({exc})"))
    for i in idx:
        if i in crcs and crcs[i] != stored[i - i0]:
            problems.append(Problem(i, store.token(i), name, "checksum mismatch"))
    return problems


def _crc_rows(data: np.ndarray) -> list[int]:
    return [zlib.crc32(np.ascontiguousarray(row).tobytes()) for row in data]


def _check_flat(store: OpenStore, off_name: str, flat_name: str, i0: int, idx: list[int],
                off: np.ndarray | None, stored: np.ndarray) -> list[Problem]:
    """Each sample's bytes of a flat array (its camera slices concatenated) against its checksum.
    The block's ranges are read in a few requests (neighbours merged), then sliced here."""
    if off is None:
        return [Problem(i, store.token(i), off_name, "unreadable offsets") for i in idx]
    flat = store[flat_name]
    spans = _merged_spans(off[[i - i0 for i in idx]], MERGE_GAP * store.integrity.chunk_rows(flat_name))
    data: list[tuple[int, int, np.ndarray]] = []
    for s, e in spans:
        try:
            data.append((s, e, np.asarray(flat[s:e])))
        except Exception:  # noqa: BLE001 - the samples in it are read one by one below
            pass
    problems: list[Problem] = []
    for i in idx:
        parts = [(int(s), int(n)) for s, n in off[i - i0] if n > 0]
        try:
            crc = zlib.crc32(b"".join(np.ascontiguousarray(_slice(flat, data, s, n)).tobytes() for s, n in parts))
        except Exception as exc:  # noqa: BLE001
            problems.append(Problem(i, store.token(i), flat_name, f"unreadable chunk ({exc})"))
            continue
        if crc != stored[i - i0]:
            problems.append(Problem(i, store.token(i), flat_name, "checksum mismatch"))
    return problems


def _merged_spans(off: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """[start, end) element spans covering every non-empty range of `off` ((n, cams, 2) int64),
    ranges less than `gap` apart merged into one."""
    pairs = off.reshape(-1, 2)
    pairs = pairs[pairs[:, 1] > 0]
    if not len(pairs):
        return []
    starts, ends = pairs[:, 0], pairs[:, 0] + pairs[:, 1]
    order = np.argsort(starts, kind="stable")
    starts, ends = starts[order], np.maximum.accumulate(ends[order])
    breaks = np.flatnonzero(starts[1:] > ends[:-1] + gap) + 1
    first, last = np.r_[0, breaks], np.r_[breaks, len(starts)] - 1
    return [(int(starts[a]), int(ends[b])) for a, b in zip(first, last, strict=True)]


def _slice(flat: zarr.Array, data: list[tuple[int, int, np.ndarray]], s: int, n: int) -> np.ndarray:
    """Elements [s, s + n) of the flat array: from a span read already, else read now."""
    for a, b, arr in data:
        if a <= s and s + n <= b:
            return arr[s - a : s - a + n]
    return np.asarray(flat[s : s + n])


def pending_samples(reader: StoreReader) -> np.ndarray:
    """Indices of samples the build has not committed yet (an interrupted or running build)."""
    return np.flatnonzero(reader.state == STATE_PENDING)
