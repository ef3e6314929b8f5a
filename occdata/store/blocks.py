"""The build's two task kinds, one block of samples each (the block is the store's chunk/shard unit).

1. `ConvertJob` -> `convert_block` (any worker, any order): converts the block's samples, writes its rows of every
   fixed-shape array (whole chunks/shards that only this block owns), then publishes its ragged
   payload (JPEG bytes, depth points), the per-sample checksums and the errors as one staging
   object `<store>.staging/block_<b>.npz` (written whole: a rename locally, one PUT on S3). It
   returns a `BlockSummary` (sizes and errors, a few bytes): no data travels through the client.
2. `CommitJob` -> `commit_block` (once the client has placed the block in the flat arrays): copies the staged
   payload into the flat arrays at its chunk-aligned start, then writes offsets, checksums and,
   last, the state flags (the commit point).

Where a block's payload goes depends on the sizes of the blocks before it (`Placer`): every block
starts on a chunk boundary, so no two tasks ever write the same chunk, and the layout is a function
of the inputs alone (any number of workers, any completion order, any kill and resume: the same
bytes). Both tasks are idempotent: a task rerun after its worker died rewrites the same bytes.
"""

from __future__ import annotations

import bisect
import io
import json
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from occdata.nuscenes import LidarRecord, SampleRecord
from occdata.runtime.storage import join, read_bytes, write_atomic
from occdata.runtime.tasks import StopCheck, no_stop
from occdata.store.layout import (
    FLAT_ARRAYS,
    FLAT_OF_OFFSETS,
    PER_SAMPLE,
    STATE_DONE,
    STATE_ERROR,
    STATE_PENDING,
    checksummed_names,
)
from occdata.store.sample import SampleOptions, SampleResult, process_sample

__all__ = ["BlockSummary", "CommitJob", "ConvertJob", "Placer", "SampleInput", "commit_block", "convert_block",
           "flat_footprint", "open_flat", "open_for_task", "sample_checksums", "staged_summary", "staging_file"]

_OFFSETS_OF_FLAT = {flat: off for off, flat in FLAT_OF_OFFSETS.items()}


@dataclass(frozen=True)
class SampleInput:
    """What converting one sample reads (`process_sample`'s arguments): its store index, its record,
    the arrays known from the tables alone (`static_arrays`), its labels file, the options and the
    previous LiDAR sweeps for the depth targets."""

    index: int
    sample: SampleRecord
    static: dict[str, np.ndarray]
    label_path: Path | None
    options: SampleOptions
    sweeps: tuple[LidarRecord, ...] = ()

    def convert(self) -> SampleResult:
        return process_sample(self.index, self.sample, self.static, self.label_path, self.options, self.sweeps)


@dataclass(frozen=True)
class ConvertJob:
    """Task 1 for samples `i0..i1-1` (block `block`), one `SampleInput` each; returns a `BlockSummary`."""

    store: str
    staging: str
    block: int
    i0: int
    i1: int
    samples: tuple[SampleInput, ...]

    @property
    def units(self) -> int:
        return self.i1 - self.i0

    def run(self, should_stop: StopCheck = no_stop) -> BlockSummary:
        return convert_block(self)  # a block takes seconds: the runner's checks between tasks suffice


@dataclass(frozen=True)
class BlockSummary:
    """What the client needs to place a block: rows per flat array, and the failed samples."""

    block: int
    rows: dict[str, int]
    errors: tuple[tuple[int, str, str], ...]  # (sample index, token, reason)


@dataclass(frozen=True)
class CommitJob:
    """Commit block `block` with its flat payloads starting at `starts` (rows, chunk-aligned);
    samples from `commit_until` on stay pending (--on-error fail stops at a failed sample)."""

    store: str
    staging: str
    block: int
    i0: int
    i1: int
    starts: dict[str, int]
    commit_until: int

    @property
    def units(self) -> int:
        return 0  # the bar counts converted samples

    def run(self, should_stop: StopCheck = no_stop) -> int:
        return commit_block(self)  # no stop inside: the commit is short, and its flags go last


def staging_file(staging: str, block: int) -> str:
    return join(staging, f"block_{block:07d}.npz")


def _fill_rows(root: zarr.Group) -> dict[str, np.ndarray]:
    return {s.name: np.full(root[s.name].shape[1:], s.fill, dtype=s.dtype) for s in PER_SAMPLE}


def open_for_task(store: str) -> zarr.Group:
    """The store's root with every array's metadata from one read (consolidated metadata). The flat
    arrays grow during a build: open them with `open_flat`, never from this group."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zarr: consolidated metadata is not (yet) in the v3 spec
        try:
            return zarr.open_group(store, mode="r+", use_consolidated=True)
        except ValueError:  # a store from before consolidated metadata
            return zarr.open_group(store, mode="r+")


def open_flat(store: str, name: str) -> zarr.Array:
    """A flat array with its current shape (its own metadata, not the consolidated copy)."""
    return zarr.open_array(store, path=name, mode="r+")


def _write_rows(writes: list[tuple[zarr.Array, int, int, np.ndarray]]) -> None:
    """`array[i0:i1] = data` for each, concurrently (on an object store each is a PUT round trip)."""
    def one(w: tuple[zarr.Array, int, int, np.ndarray]) -> None:
        w[0][w[1] : w[2]] = w[3]

    with ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(one, writes))


def convert_block(job: ConvertJob) -> BlockSummary:
    """Task 1: convert, write the fixed-shape rows, publish the staging object."""
    results = [sample.convert() for sample in job.samples]
    root = open_for_task(job.store)
    fill = _fill_rows(root)
    block: dict[str, np.ndarray] = {}
    for s in PER_SAMPLE:
        if s.name.startswith("status/"):
            continue
        if s.name in FLAT_OF_OFFSETS:
            block[s.name] = np.zeros((len(results), *root[s.name].shape[1:]), dtype=s.dtype)  # set at commit
            continue
        block[s.name] = np.stack([r.arrays.get(s.name, fill[s.name]) for r in results]).astype(s.dtype, copy=False)
    _write_rows([(root[n], job.i0, job.i1, a) for n, a in block.items() if n not in FLAT_OF_OFFSETS])
    payload = _payload(results)
    names = checksummed_names()
    sums = np.zeros((len(results), len(names)), dtype=np.uint32)
    for k in range(len(results)):
        for col, name in enumerate(names):
            if name in FLAT_ARRAYS:
                sums[k, col] = zlib.crc32(payload[f"{name}/sample_bytes"][k])
            elif name not in FLAT_OF_OFFSETS:
                sums[k, col] = zlib.crc32(np.ascontiguousarray(block[name][k]).tobytes())
    errors = tuple((r.index, r.token, r.error) for r in results if r.error)
    buf = io.BytesIO()
    np.savez(buf, checksums=sums, errors=np.array(json.dumps(errors)),
             **{f"{n}/data": payload[f"{n}/data"] for n in FLAT_ARRAYS},
             **{f"{n}/rows": payload[f"{n}/rows"] for n in FLAT_ARRAYS})
    write_atomic(staging_file(job.staging, job.block), buf.getvalue())
    return BlockSummary(job.block, {n: int(payload[f"{n}/rows"].sum()) for n in FLAT_ARRAYS}, errors)


def sample_checksums(arrays: dict[str, np.ndarray], flat: dict[str, bytes]) -> np.ndarray:
    """`(A,) uint32` crc32 per checksummed array, in `checksummed_names()` order."""
    out = []
    for name in checksummed_names():
        if name in FLAT_ARRAYS:
            out.append(zlib.crc32(flat[name]))
        else:
            out.append(zlib.crc32(np.ascontiguousarray(arrays[name]).tobytes()))
    return np.array(out, dtype=np.uint32)


def _payload(results: list[SampleResult]) -> dict[str, Any]:
    """Per flat array: `data` (all rows, sample then camera order), `rows` `(n, 6) int64` per
    (sample, camera), `sample_bytes` (the checksummed bytes of each sample)."""
    out: dict[str, Any] = {}
    for name, (row_shape, dtype, _) in FLAT_ARRAYS.items():
        row_bytes = int(np.dtype(dtype).itemsize * int(np.prod(row_shape, dtype=np.int64)))
        rows = np.zeros((len(results), 6), dtype=np.int64)
        per_sample = []
        for k, r in enumerate(results):
            parts = list(r.jpeg) if name == "images/jpeg" else [u.tobytes() for u in r.uvd]
            for c, part in enumerate(parts):
                rows[k, c] = len(part) // row_bytes
            per_sample.append(b"".join(parts))
        blob = b"".join(per_sample)
        out[f"{name}/data"] = np.frombuffer(blob, dtype=dtype).reshape((-1, *row_shape))
        out[f"{name}/rows"] = rows
        out[f"{name}/sample_bytes"] = per_sample
    return out


def _load_staged(staging: str, block: int) -> dict[str, np.ndarray] | None:
    raw = read_bytes(staging_file(staging, block))
    if raw is None:
        return None
    with np.load(io.BytesIO(raw), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def staged_summary(staging: str, block: int) -> BlockSummary | None:
    """The summary of a block an earlier (interrupted) run converted, or None."""
    try:
        z = _load_staged(staging, block)
    except (OSError, ValueError, KeyError):  # a damaged staging object: convert the block again
        return None
    if z is None:
        return None
    errors = tuple(tuple(e) for e in json.loads(str(z["errors"])))
    return BlockSummary(block, {n: int(z[f"{n}/rows"].sum()) for n in FLAT_ARRAYS}, errors)  # type: ignore[arg-type]


def commit_block(job: CommitJob) -> int:
    """Task 2: flat payloads, offsets, checksums, then the state flags. Returns samples committed."""
    z = _load_staged(job.staging, job.block)
    if z is None:
        where = staging_file(job.staging, job.block)
        raise FileNotFoundError(f"the staging object of block {job.block} is missing: {where}")
    root = open_for_task(job.store)
    sums = z["checksums"].copy()
    writes: list[tuple[zarr.Array, int, int, np.ndarray]] = []
    names = checksummed_names()
    for name, (row_shape, dtype, chunk_rows) in FLAT_ARRAYS.items():
        data, rows, start = z[f"{name}/data"], z[f"{name}/rows"], job.starts[name]
        if len(data):
            padded = np.zeros((_align(len(data), chunk_rows), *row_shape), dtype=dtype)
            padded[: len(data)] = data
            open_flat(job.store, name)[start : start + len(padded)] = padded  # whole chunks: no read-modify-write
        ends = start + np.cumsum(rows.reshape(-1)).reshape(rows.shape)
        offsets = np.stack([ends - rows, rows], axis=-1).astype(np.int64)  # (n, 6, 2): start, rows
        off_name = _OFFSETS_OF_FLAT[name]
        writes.append((root[off_name], job.i0, job.i1, offsets))
        col = names.index(off_name)
        sums[:, col] = [zlib.crc32(np.ascontiguousarray(o).tobytes()) for o in offsets]
    writes.append((root["status/checksum"], job.i0, job.i1, sums))
    _write_rows(writes)  # offsets and checksums before the state flags
    failed = {int(i) for i, _, _ in json.loads(str(z["errors"]))}
    state = np.array([STATE_PENDING if i >= job.commit_until else STATE_ERROR if i in failed else STATE_DONE
                      for i in range(job.i0, job.i1)], dtype=np.uint8)
    root["status/state"].with_config({"write_empty_chunks": True})[job.i0 : job.i1] = state
    return int((state != STATE_PENDING).sum())


def _align(n: int, chunk: int) -> int:
    return -(-n // chunk) * chunk


def flat_footprint(offsets: np.ndarray, chunk_rows: int) -> tuple[int, int] | None:
    """The chunk-aligned row range `[start, end)` that a committed block's `(n, 6, 2)` offsets use."""
    used = offsets[..., 1] > 0
    if not used.any():
        return None
    lo = int(offsets[..., 0][used].min())
    hi = int((offsets[..., 0] + offsets[..., 1])[used].max())
    return lo // chunk_rows * chunk_rows, _align(hi, chunk_rows)


class Placer:
    """Chunk-aligned placement of blocks in one flat array, in block order: each block goes at the
    first free, chunk-aligned position at or after the end of the block before it, avoiding the
    ranges that committed blocks occupy. A fresh build packs the blocks back to back; a resumed
    one puts each block where an uninterrupted build would have put it (same inputs, same sizes)."""

    def __init__(self, chunk_rows: int, occupied: list[tuple[int, int]]) -> None:
        self.chunk = chunk_rows
        self.occupied = sorted(occupied)
        self.cursor = 0
        self.high = max((e for _, e in occupied), default=0)

    def skip(self, footprint: tuple[int, int] | None) -> None:
        """A committed block: the next block starts after it."""
        if footprint is not None:
            self.cursor = max(self.cursor, footprint[1])

    def place(self, rows: int) -> int:
        need = _align(rows, self.chunk)
        start = _align(self.cursor, self.chunk)
        if need:
            k = bisect.bisect_left(self.occupied, (start, start))
            k = max(0, k - 1)
            while k < len(self.occupied):
                a, e = self.occupied[k]
                if a < start + need and start < e:
                    start = _align(e, self.chunk)
                elif a >= start + need:
                    break
                k += 1
            bisect.insort(self.occupied, (start, start + need))
        self.cursor = start + need
        self.high = max(self.high, self.cursor)
        return start
