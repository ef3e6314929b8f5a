"""`occdata verify`: every committed sample's chunks present and its checksums recomputed."""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from occdata.errors import OccDataError
from occdata.store.layout import FLAT_ARRAYS, FLAT_OF_OFFSETS, STATE_PENDING, checksummed_names, per_sample
from occdata.store.reader import StoreReader

__all__ = ["Problem", "pending_samples", "verify_store"]


@dataclass(frozen=True)
class Problem:
    index: int
    token: str
    array: str
    reason: str


def _crc_rows(data: np.ndarray) -> list[int]:
    return [zlib.crc32(np.ascontiguousarray(row).tobytes()) for row in data]


def verify_store(reader: StoreReader, block: int = 32, progress: Callable[[int], None] | None = None) -> list[Problem]:
    """Missing chunks, checksum mismatches and unreadable chunks, each with the sample it belongs to.

    Raises `OccDataError` when the commit flags themselves are missing or unreadable (then no
    sample can be judged). Pending samples are not problems: see `pending_samples`.
    """
    state = reader.state  # checked: a missing state chunk in a complete store raises
    try:
        stored = reader.group["status/checksum"][:]
    except Exception as exc:  # noqa: BLE001
        raise OccDataError(f"status arrays of {reader.path} are unreadable: {exc}") from None
    names = checksummed_names(reader.has_flow)
    if stored.shape[1] != len(names):
        raise OccDataError(f"{reader.path}: checksum table has {stored.shape[1]} columns, expected {len(names)}")
    problems: list[Problem] = []
    # Every array's chunks: an absent one must hold only fill values for each committed sample.
    specs = per_sample(reader.has_flow, reader.grid_shape, reader.n_cams)
    for name in [s.name for s in specs if s.name != "status/state"] + list(FLAT_ARRAYS):
        try:
            absent = reader.integrity.problems_absent(name, state)
        except OccDataError as exc:
            problems.append(Problem(-1, "?", name, str(exc)))
            continue
        problems += [Problem(i, _token(reader, i), name, why) for i, why in absent]
    committed = state != STATE_PENDING
    offsets = {}
    for off_name in FLAT_OF_OFFSETS:
        try:
            offsets[off_name] = reader.group[off_name][:]
        except Exception:  # noqa: BLE001 - reported per sample below
            offsets[off_name] = None
    for i0 in range(0, reader.n_samples, block):
        i1 = min(i0 + block, reader.n_samples)
        idx = [i for i in range(i0, i1) if committed[i]]
        if not idx:
            if progress:
                progress(i1 - i0)
            continue
        for col, name in enumerate(names):
            if name in FLAT_ARRAYS:
                continue
            try:
                crcs = dict(zip(range(i0, i1), _crc_rows(reader.group[name][i0:i1]), strict=True))
            except Exception:  # noqa: BLE001 - find the bad sample(s) one by one
                crcs = {}
                for i in idx:
                    try:
                        crcs[i] = _crc_rows(reader.group[name][i : i + 1])[0]
                    except Exception as exc:  # noqa: BLE001
                        problems.append(Problem(i, _token(reader, i), name, f"unreadable chunk ({exc})"))
            for i in idx:
                if i in crcs and crcs[i] != stored[i, col]:
                    problems.append(Problem(i, _token(reader, i), name, "checksum mismatch"))
        for off_name, flat_name in FLAT_OF_OFFSETS.items():
            col = names.index(flat_name)
            for i in idx:
                off = offsets[off_name]
                if off is None:
                    problems.append(Problem(i, _token(reader, i), off_name, "unreadable offsets"))
                    continue
                try:
                    parts = [reader.group[flat_name][int(s) : int(s) + int(n)] for s, n in off[i] if n]
                    crc = zlib.crc32(b"".join(np.ascontiguousarray(p).tobytes() for p in parts))
                except Exception as exc:  # noqa: BLE001
                    problems.append(Problem(i, _token(reader, i), flat_name, f"unreadable chunk ({exc})"))
                    continue
                if crc != stored[i, col]:
                    problems.append(Problem(i, _token(reader, i), flat_name, "checksum mismatch"))
        if progress:
            progress(i1 - i0)
    return problems


def _token(reader: StoreReader, i: int) -> str:
    try:
        return reader.token(i)
    except Exception:  # noqa: BLE001 - the token array itself may be the corrupt one
        return "?"


def pending_samples(reader: StoreReader) -> np.ndarray:
    """Indices of samples the build has not committed yet (an interrupted or running build)."""
    return np.flatnonzero(reader.state == STATE_PENDING)
