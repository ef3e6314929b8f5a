"""`occdata verify`: every committed sample's chunks present and its checksums recomputed.

Two parts. The client lists each array's chunks once and judges the absent ones (`StoreIntegrity`:
listings and the small arrays only). The checksums, which read every byte of the store, run as
`VerifyJob` tasks of `task_samples` samples on `occdata.runtime.cluster.run_tasks`: in this process
(`client` None) or on Dask workers, as the build's blocks do. A task opens the store itself and reads
only its own rows, so nothing of the store's size travels; its problems come back and are put in
sample order, so the report is the same for any number of workers.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from occdata.errors import OccDataError
from occdata.runtime.cluster import run_tasks
from occdata.runtime.tasks import StopCheck
from occdata.store.layout import (
    FLAT_ARRAYS,
    FLAT_OF_OFFSETS,
    STATE_PENDING,
    checksummed_names,
    has_flow,
    per_sample,
    token_str,
)
from occdata.store.reader import StoreReader

__all__ = ["Problem", "VerifyJob", "pending_samples", "verify_rows", "verify_store"]

TASK_SAMPLES = 256  # samples per task at most: a few hundred MB read, ~1-5 s on one core; blocks of 32 inside


@dataclass(frozen=True)
class Problem:
    index: int
    token: str
    array: str
    reason: str


def _crc_rows(data: np.ndarray) -> list[int]:
    return [zlib.crc32(np.ascontiguousarray(row).tobytes()) for row in data]


@dataclass(frozen=True)
class VerifyJob:
    """The checksums of samples [`i0`, `i1`) of the store at `store` (a path or URL), read `block`
    samples at a time: one task (picklable, small)."""

    store: str
    i0: int
    i1: int
    block: int = 32

    def __post_init__(self) -> None:
        if not 0 <= self.i0 <= self.i1 or self.block < 1:
            raise OccDataError(f"verify task [{self.i0}, {self.i1}) with blocks of {self.block}: not a sample range")

    @property
    def units(self) -> int:
        return self.i1 - self.i0

    def run(self, should_stop: StopCheck) -> tuple[Problem, ...]:
        group = StoreReader(self.store).group  # the layout checked again: a worker sees what the client saw
        out: list[Problem] = []
        for b0 in range(self.i0, self.i1, self.block):
            should_stop()
            out += verify_rows(group, b0, min(b0 + self.block, self.i1))
        return tuple(out)


def verify_store(reader: StoreReader, block: int = 32, progress: Callable[[int], None] | None = None,
                 client: Any = None, task_samples: int = TASK_SAMPLES) -> list[Problem]:
    """Missing chunks, checksum mismatches and unreadable chunks, each with the sample it belongs to,
    in sample order after the chunk-presence problems. `client`: a `distributed.Client` that runs the
    checksum tasks (None: this process); the result does not depend on it.

    Raises `OccDataError` when the commit flags themselves are missing or unreadable (then no
    sample can be judged). Pending samples are not problems: see `pending_samples`.
    """
    state = reader.state  # checked: a missing state chunk in a complete store raises
    try:
        stored = reader.group["status/checksum"][:]  # (n, columns) uint32: 4 bytes per sample and array
    except Exception as exc:  # noqa: BLE001
        raise OccDataError(f"status arrays of {reader.path} are unreadable: {exc}") from None
    names = checksummed_names(reader.has_flow)
    if stored.shape[1] != len(names):
        raise OccDataError(f"{reader.path}: checksum table has {stored.shape[1]} columns, expected {len(names)}")
    problems = _absent_problems(reader, state)
    # Whole blocks per task (a chunk is never read by two tasks), at most `task_samples`, and at least
    # ~16 tasks where the store has the blocks: two workers given two large tasks finish unevenly.
    spread = -(-reader.n_samples // (16 * block)) * block
    step = max(block, min(task_samples // block * block, spread))
    jobs = [VerifyJob(str(reader.path), i0, min(i0 + step, reader.n_samples), block)
            for i0 in range(0, reader.n_samples, step)]
    found: dict[int, tuple[Problem, ...]] = {}

    def on_result(job: VerifyJob, result: tuple[Problem, ...]) -> None:
        found[job.i0] = result
        if progress:
            progress(job.units)

    run_tasks(client, jobs, desc="verify", unit="sample", progress=False, on_result=on_result)
    return problems + [p for i0 in sorted(found) for p in found[i0]]


def _absent_problems(reader: StoreReader, state: np.ndarray) -> list[Problem]:
    """Every array's chunks: an absent one must hold only fill values for each committed sample."""
    problems: list[Problem] = []
    specs = per_sample(reader.has_flow, reader.grid_shape, reader.n_cams)
    for name in [s.name for s in specs if s.name != "status/state"] + list(FLAT_ARRAYS):
        try:
            absent = reader.integrity.problems_absent(name, state)
        except OccDataError as exc:
            problems.append(Problem(-1, "?", name, str(exc)))
            continue
        problems += [Problem(i, _token(reader.group, i), name, why) for i, why in absent]
    return problems


def verify_rows(group: zarr.Group, i0: int, i1: int) -> list[Problem]:
    """The checksum problems of the committed samples in [`i0`, `i1`) of an open store `group`: each
    checksummed array's rows and each sample's flat-array bytes recomputed against `status/checksum`.
    Reads only these rows (and their flat-array ranges)."""
    try:
        state = np.asarray(group["status/state"][i0:i1])
        stored = np.asarray(group["status/checksum"][i0:i1])
    except Exception as exc:  # noqa: BLE001 - the client read them whole a moment ago: a store changing under us
        return [Problem(i0, "?", "status/checksum", f"unreadable chunk ({exc})")]
    idx = [i for i in range(i0, i1) if state[i - i0] != STATE_PENDING]
    if not idx:
        return []
    names = checksummed_names(has_flow(dict(group.attrs)))
    problems: list[Problem] = []
    for col, name in enumerate(names):
        if name not in FLAT_ARRAYS:
            problems += _check_array(group, name, i0, i1, idx, stored[:, col])
    for off_name, flat_name in FLAT_OF_OFFSETS.items():
        problems += _check_flat(group, off_name, flat_name, i0, i1, idx, stored[:, names.index(flat_name)])
    return sorted(problems, key=lambda p: p.index)


def _check_array(group: zarr.Group, name: str, i0: int, i1: int, idx: list[int],
                 stored: np.ndarray) -> list[Problem]:
    """Rows of a per-sample array against their checksums (`stored`: rows i0..i1 of the column)."""
    problems: list[Problem] = []
    try:
        crcs = dict(zip(range(i0, i1), _crc_rows(group[name][i0:i1]), strict=True))
    except Exception:  # noqa: BLE001 - find the bad sample(s) one by one
        crcs = {}
        for i in idx:
            try:
                crcs[i] = _crc_rows(group[name][i : i + 1])[0]
            except Exception as exc:  # noqa: BLE001
                problems.append(Problem(i, _token(group, i), name, f"unreadable chunk ({exc})"))
    for i in idx:
        if i in crcs and crcs[i] != stored[i - i0]:
            problems.append(Problem(i, _token(group, i), name, "checksum mismatch"))
    return problems


def _check_flat(group: zarr.Group, off_name: str, flat_name: str, i0: int, i1: int, idx: list[int],
                stored: np.ndarray) -> list[Problem]:
    """Each sample's bytes of a flat array (its camera slices concatenated) against its checksum."""
    try:
        off = np.asarray(group[off_name][i0:i1])
    except Exception:  # noqa: BLE001 - reported per sample
        return [Problem(i, _token(group, i), off_name, "unreadable offsets") for i in idx]
    flat = group[flat_name]
    problems: list[Problem] = []
    for i in idx:
        try:
            parts = [flat[int(s) : int(s) + int(n)] for s, n in off[i - i0] if n]
            crc = zlib.crc32(b"".join(np.ascontiguousarray(p).tobytes() for p in parts))
        except Exception as exc:  # noqa: BLE001
            problems.append(Problem(i, _token(group, i), flat_name, f"unreadable chunk ({exc})"))
            continue
        if crc != stored[i - i0]:
            problems.append(Problem(i, _token(group, i), flat_name, "checksum mismatch"))
    return problems


def _token(group: zarr.Group, i: int) -> str:
    """Sample `i`'s token, one row read (a task holds no token table); "?" where unreadable."""
    try:
        return token_str(np.asarray(group["sample/token"][i]))
    except Exception:  # noqa: BLE001 - the token array itself may be the corrupt one
        return "?"


def pending_samples(reader: StoreReader) -> np.ndarray:
    """Indices of samples the build has not committed yet (an interrupted or running build)."""
    return np.flatnonzero(reader.state == STATE_PENDING)
