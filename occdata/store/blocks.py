"""The build's task: one block of samples (the block is the store's chunk/shard unit), written once.

`ConvertJob` -> `convert_block` (any worker, any order, any number of times): converts the block's
samples, writes its rows of every fixed-shape array (whole chunks/shards that only this block owns),
writes its ragged payload (JPEG bytes, depth points) straight into the block's region of the flat
arrays (planned by the client from the inputs before any task ran, `occdata.store.plan`), then the
offsets and checksums and, last, the state flags (the commit point). Every byte is written once,
where readers find it; nothing is staged or copied, and no task waits for another.

A region starts on a chunk boundary and is never shared, so the layout is a function of the inputs
alone (any number of workers, any completion order, any kill and resume: the same bytes). A payload
that does not fit its region (an input file grew since the plan was made) is not written: the task
reports its size and the client gives the block a new region (`occdata.store.plan.relocate`).
"""

from __future__ import annotations

import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.core.sync import sync

from occdata.errors import OccDataError
from occdata.formats.gridspec import GridSpec
from occdata.nuscenes import LidarRecord, SampleRecord
from occdata.runtime.lock import Fence
from occdata.runtime.tasks import StopCheck, no_stop
from occdata.store.layout import (
    FLAT_ARRAYS,
    FLAT_OF_OFFSETS,
    STATE_DONE,
    STATE_ERROR,
    STATE_PENDING,
    camera_count,
    checksummed_names,
    grid_shape,
    has_flow,
    per_sample,
)
from occdata.store.sample import SampleOptions, SampleResult, process_sample

__all__ = ["BlockSummary", "ConvertJob", "SampleInput", "convert_block", "open_for_task", "sample_checksums"]

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
    label_format: str = "occ3d"  # "openocc-v2": OpenOcc v2 files, with flow (occdata.formats.occ3d)
    grid: GridSpec | None = None  # the labels files' grid when not Occ3D's (occdata.formats.gridfiles)

    def convert(self) -> SampleResult:
        return process_sample(self.index, self.sample, self.static, self.label_path, self.options, self.sweeps,
                              self.label_format, self.grid)


@dataclass(frozen=True)
class ConvertJob:
    """The task for samples `i0..i1-1` (block `block`), one `SampleInput` each; `regions`: the block's
    [start, end) rows in each flat array (FLAT_ARRAYS order, chunk-aligned starts); `on_error`: under
    "fail" the samples from the block's first failed one on stay pending; `fence`: the run's, checked
    before each array write (a task left running once the run stopped or lost its lease writes nothing
    more). Returns a `BlockSummary`."""

    store: str
    block: int
    i0: int
    i1: int
    samples: tuple[SampleInput, ...]
    regions: tuple[tuple[int, int], ...]
    on_error: str = "skip"
    fence: Fence | None = None

    def __post_init__(self) -> None:
        if len(self.samples) != self.i1 - self.i0:
            raise OccDataError(f"block {self.block}: {len(self.samples)} samples for indices {self.i0}..{self.i1 - 1}")
        if len(self.regions) != len(FLAT_ARRAYS) or any(
                not 0 <= a <= e or a % chunk for (a, e), (_, _, chunk) in zip(self.regions, FLAT_ARRAYS.values(),
                                                                                strict=False)):
            raise OccDataError(f"block {self.block}: regions {self.regions} are not chunk-aligned ranges")
        if self.on_error not in ("fail", "skip"):
            raise OccDataError(f"on_error must be fail or skip, got {self.on_error!r}")

    @property
    def units(self) -> int:
        return self.i1 - self.i0

    def run(self, should_stop: StopCheck = no_stop) -> BlockSummary:
        return convert_block(self)  # a block takes seconds: the runner's checks between tasks suffice


@dataclass(frozen=True)
class BlockSummary:
    """What comes back to the client: the failed samples (index, token, reason), the block's rows per
    flat array (`needs`), and whether it was written (`placed`; False: it outgrew its region, nothing
    of the flat arrays nor the flags was written)."""

    block: int
    errors: tuple[tuple[int, str, str], ...]
    needs: tuple[int, ...]
    placed: bool = True


def _fill_rows(root: zarr.Group, specs: tuple) -> dict[str, np.ndarray]:
    return {s.name: np.full(root[s.name].shape[1:], s.fill, dtype=s.dtype) for s in specs}


def open_for_task(store: str) -> zarr.Group:
    """The store's root with every array's metadata from one read (consolidated metadata; the client
    rewrites it before any task runs and whenever an array grows)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zarr: consolidated metadata is not (yet) in the v3 spec
        try:
            return zarr.open_group(store, mode="r+", use_consolidated=True)
        except ValueError:  # a store from before consolidated metadata
            return zarr.open_group(store, mode="r+")


def _fenced(fence: Fence | None) -> None:
    if fence is not None:
        fence.check()


def _write_rows(writes: list[tuple[zarr.Array, int, int, np.ndarray]], fence: Fence | None,
                kinds: dict[str, str] | None = None) -> None:
    """`array[i0:i1] = data` for each, concurrently (on an object store each is a PUT round trip),
    each after checking `fence`. `kinds` (`_fill_kinds`) spares zarr's all-fill comparison of every
    chunk, which for the 640 KB label rows was ~15% of a build's CPU, on zarr's one IO thread: rows that
    are all data are written with `write_empty_chunks` (the same chunks are stored), rows that are all
    fill delete their chunks (what zarr would do). Mixed rows keep zarr's default: an unlabelled
    sample's label chunk stays absent."""
    kinds = kinds or {}

    def one(w: tuple[zarr.Array, int, int, np.ndarray]) -> None:
        arr, i0, i1, data = w
        kind = kinds.get(arr.path.strip("/"), "mixed")
        _fenced(fence)
        if kind == "fill" and _clear_rows(arr, i0, i1):
            return
        (arr.with_config({"write_empty_chunks": True}) if kind == "data" else arr)[i0:i1] = data

    with ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(one, writes))


def convert_block(job: ConvertJob) -> BlockSummary:
    """Convert, write the fixed-shape rows, then (if it fits its region) the payload, offsets,
    checksums and last the state flags."""
    results = [sample.convert() for sample in job.samples]
    root = open_for_task(job.store)
    flow, n_cams = has_flow(root.attrs), camera_count(root.attrs)
    specs = per_sample(flow, grid_shape(root.attrs), n_cams)
    fill = _fill_rows(root, specs)  # each array's fill row: for samples without it, and the kinds below
    rows = _fixed_rows(results, specs, fill)
    names = checksummed_names(flow)
    sums = np.zeros((len(results), len(names)), dtype=np.uint32)
    for col, name in enumerate(names):
        if name in rows:
            sums[:, col] = [zlib.crc32(np.ascontiguousarray(row).tobytes()) for row in rows[name]]
    _write_rows([(root[n], job.i0, job.i1, a) for n, a in rows.items()], job.fence,
                _fill_kinds(fill, names, sums))
    payload = _payload(results, n_cams)
    errors = tuple((r.index, r.token, r.error) for r in results if r.error)
    needs = tuple(int(payload[f"{n}/rows"].sum()) for n in FLAT_ARRAYS)
    if any(need > e - a for need, (a, e) in zip(needs, job.regions, strict=True)):
        return BlockSummary(job.block, errors, needs, placed=False)
    for col, name in enumerate(names):
        if name in FLAT_ARRAYS:
            sums[:, col] = [zlib.crc32(b) for b in payload[f"{name}/sample_bytes"]]
    writes: list[tuple[zarr.Array, int, int, np.ndarray]] = []
    for (name, (row_shape, dtype, chunk)), (start, _) in zip(FLAT_ARRAYS.items(), job.regions, strict=True):
        data, counts = payload[f"{name}/data"], payload[f"{name}/rows"]
        if len(data):  # whole chunks from the region's start: no read-modify-write, no chunk shared
            padded = np.zeros((-(-len(data) // chunk) * chunk, *row_shape), dtype=dtype)
            padded[: len(data)] = data
            _fenced(job.fence)
            # write_empty_chunks: skips zarr's all-fill scan of every chunk (payload is never all zeros)
            root[name].with_config({"write_empty_chunks": True})[start : start + len(padded)] = padded
        ends = start + np.cumsum(counts.reshape(-1)).reshape(counts.shape)
        offsets = np.stack([ends - counts, counts], axis=-1).astype(np.int64)  # (n, 6, 2): start, rows
        writes.append((root[_OFFSETS_OF_FLAT[name]], job.i0, job.i1, offsets))
        sums[:, names.index(_OFFSETS_OF_FLAT[name])] = [zlib.crc32(np.ascontiguousarray(o).tobytes())
                                                        for o in offsets]
    writes.append((root["status/checksum"], job.i0, job.i1, sums))
    _write_rows(writes, job.fence)  # offsets and checksums before the state flags
    _fenced(job.fence)
    root["status/state"].with_config({"write_empty_chunks": True})[job.i0 : job.i1] = _flags(job, errors)
    return BlockSummary(job.block, errors, needs)


def _fill_kinds(fill: dict[str, np.ndarray], names: tuple[str, ...], sums: np.ndarray) -> dict[str, str]:
    """For each checksummed fixed-shape array (`fill`: its fill row, `_fill_rows`), whether this block's
    rows are all "data" (none is the fill row, by checksum; `sums`: `(n, len(names)) uint32`), all
    "fill", or "mixed"."""
    kinds = {}
    for col, name in enumerate(names):
        if name in fill:
            is_fill = sums[:, col] == zlib.crc32(np.ascontiguousarray(fill[name]).tobytes())
            kinds[name] = "fill" if is_fill.all() else "mixed" if is_fill.any() else "data"
    return kinds


def _clear_rows(arr: zarr.Array, i0: int, i1: int) -> bool:
    """Delete the stored chunks (shards) of rows `i0..i1-1`, as zarr does for an all-fill write,
    when the rows cover whole ones; False (nothing done) when they do not."""
    step = (arr.shards or arr.chunks)[0]
    whole_rows = tuple((arr.shards or arr.chunks)[1:]) == tuple(arr.shape[1:])
    if not whole_rows or i0 % step or (i1 % step and i1 != arr.shape[0]):
        return False
    zeros = (0,) * (arr.ndim - 1)
    for k in range(i0 // step, -(-i1 // step)):
        sync((arr.store_path / arr.metadata.encode_chunk_key((k, *zeros))).delete())
    return True


def _fixed_rows(results: list[SampleResult], specs: tuple, fill: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The block's rows of every fixed-shape array of `specs` but offsets and status, `(n, ...)` each
    (`fill`: the row of a sample without the array)."""
    return {s.name: np.stack([r.arrays.get(s.name, fill[s.name]) for r in results]).astype(s.dtype, copy=False)
            for s in specs if not s.name.startswith("status/") and s.name not in FLAT_OF_OFFSETS}


def _flags(job: ConvertJob, errors: tuple[tuple[int, str, str], ...]) -> np.ndarray:
    """`(n,) uint8` state: done, or error (skip); under fail, pending from the first failed sample on."""
    failed = {i for i, _, _ in errors}
    until = min(failed) if failed and job.on_error == "fail" else job.i1
    return np.array([STATE_PENDING if i >= until else STATE_ERROR if i in failed else STATE_DONE
                     for i in range(job.i0, job.i1)], dtype=np.uint8)


def sample_checksums(arrays: dict[str, np.ndarray], flat: dict[str, bytes], flow: bool = False) -> np.ndarray:
    """`(A,) uint32` crc32 per checksummed array, in `checksummed_names(flow)` order."""
    out = []
    for name in checksummed_names(flow):
        if name in FLAT_ARRAYS:
            out.append(zlib.crc32(flat[name]))
        else:
            out.append(zlib.crc32(np.ascontiguousarray(arrays[name]).tobytes()))
    return np.array(out, dtype=np.uint32)


def _payload(results: list[SampleResult], n_cams: int) -> dict[str, Any]:
    """Per flat array: `data` (all rows, sample then camera order), `rows` `(n, C) int64` per
    (sample, camera), `sample_bytes` (the checksummed bytes of each sample)."""
    out: dict[str, Any] = {}
    for name, (row_shape, dtype, _) in FLAT_ARRAYS.items():
        row_bytes = int(np.dtype(dtype).itemsize * int(np.prod(row_shape, dtype=np.int64)))
        rows = np.zeros((len(results), n_cams), dtype=np.int64)
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
