"""`occdata build`: a nuScenes-format tree (+ Occ3D labels) -> one chunked zarr store.

The work runs as tasks on Dask (`occdata.runtime.cluster`): one block of `--block-samples` samples per task,
aligned to the store's chunks and shards, each task writing its own chunks (`occdata.store.blocks`):
many writers, and only sizes and errors travel back to this process, which places the blocks'
ragged payloads (chunk-aligned, in block order) and owns the metadata. A sample is complete only
once its state flag says so; `--resume` commits what an interrupted run converted, converts the
rest, and gives a store identical to an uninterrupted build, for any number of workers.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import warnings
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zarr
from zarr.codecs import ZstdCodec
from zarr.core.sync import sync

from occdata.constants import CAMERA_ORDER, CLASS_COLORS, CLASS_NAMES, FREE_LABEL, GRID
from occdata.errors import OccDataError
from occdata.nuscenes import LidarRecord, NuScenesDataset, load_nuscenes
from occdata.nuscenes.reader import confined_path
from occdata.runtime.cluster import ClusterConfig, cluster_client, run_tasks
from occdata.runtime.lock import store_lock
from occdata.runtime.storage import is_remote, join, read_bytes, remove_tree, sibling
from occdata.store.blocks import (
    BlockSummary,
    CommitJob,
    ConvertJob,
    Placer,
    flat_footprint,
    open_flat,
    run_job,
    staged_summary,
)
from occdata.store.layout import (
    FLAT_ARRAYS,
    FLAT_OF_OFFSETS,
    PER_SAMPLE,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    STATE_DONE,
    STATE_ERROR,
    STATE_PENDING,
    TOKEN_ARRAYS,
    checksummed_names,
    token_width,
)
from occdata.store.reader import StoreReader, store_location
from occdata.store.sample import SampleOptions, static_arrays, temporal_indices

__all__ = ["BuildConfig", "BuildReport", "build_store", "check_sweep_files", "find_label_files", "identity_diff",
           "label_layouts", "sample_checksums"]


@dataclass(frozen=True)
class BuildConfig:
    root: Path
    out: Path | str  # a folder, or an fsspec URL (s3://bucket/data.zarr)
    version: str | None = None
    gts: Path | None = None
    # With labels_required (an explicit --gts), a labels folder in which no sample finds its file
    # is an error (a wrong folder would give a silently unlabelled store); off for the default
    # <root>/gts, which may legitimately hold no labels for the selected split (test).
    labels_required: bool = True
    splits: tuple[str, ...] = ()
    workers: int = 1  # LocalCluster worker processes (1: in this process)
    scheduler: str | None = None  # an existing Dask scheduler (tcp://host:8786); None: $DASK_SCHEDULER_ADDRESS
    resume: bool = False
    on_error: Literal["fail", "skip"] = "fail"
    block_samples: int = 32
    options: SampleOptions = field(default_factory=SampleOptions)
    progress: bool = True


@dataclass(frozen=True)
class BuildReport:
    store: Path
    n_samples: int
    n_done: int
    n_errors: int
    n_labelled: int
    processed_now: int
    warnings: tuple[str, ...] = ()  # from reading the tables (identical duplicates, nbr_samples)


def _identity(config: BuildConfig, ds: NuScenesDataset) -> dict[str, Any]:
    """What a resumed build must match (workers, resume and on_error may change between runs)."""
    return {
        "source_root": str(ds.root),
        "source_version": ds.version,
        "gts": str(Path(config.gts).resolve()) if config.gts else None,
        "splits": list(config.splits),
        "block_samples": config.block_samples,
        "options": asdict(config.options),
        "sample_tokens_crc32": zlib.crc32("".join(s.token for s in ds.samples).encode()),
    }


# build_identity key -> what the user changes to change it
_IDENTITY_OPTION = {
    "source_root": "--root", "source_version": "--version", "gts": "--gts", "splits": "--split",
    "block_samples": "--block-samples", "options.image_scale": "--image-scale",
    "options.jpeg_quality": "--jpeg-quality", "options.min_depth": "min_depth",
    "options.lidar_sweeps": "--lidar-sweeps",
    "sample_tokens_crc32": "the sample list in the tables",
}


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def identity_diff(stored: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """One phrase per differing input/option: `--image-scale: store 1.0, now 0.5`."""
    a, b = _flatten(stored), _flatten(now)
    out = []
    for key in sorted(set(a) | set(b), key=lambda k: list(_IDENTITY_OPTION).index(k) if k in _IDENTITY_OPTION else 99):
        if a.get(key, "<unset>") != b.get(key, "<unset>"):
            if key == "sample_tokens_crc32":
                out.append("the sample list in the tables differs (tables edited?)")
            else:
                was, now_ = a.get(key, "<unset>"), b.get(key, "<unset>")
                out.append(f"{_IDENTITY_OPTION.get(key, key)}: store {was!r}, now {now_!r}")
    return out


def _compressor(name: str) -> Any:
    return None if name == "images/jpeg" else ZstdCodec(level=1)


def _create(root: zarr.Group, n: int, block: int, attrs: dict[str, Any], tok_width: int) -> None:
    n_check = len(checksummed_names())
    for s in PER_SAMPLE:
        shape = (n, *s.shape)
        if s.name == "status/checksum":
            shape = (n, n_check)
        if s.name in TOKEN_ARRAYS:  # tokens are stored whole, however long
            shape = (*shape[:-1], tok_width)
        if s.sharded:
            chunks, shards = (1, *shape[1:]), (min(block, n), *shape[1:])
        else:
            chunks, shards = (min(block, n), *shape[1:]), None
        root.create_array(
            s.name, shape=shape, dtype=s.dtype, chunks=chunks, shards=shards,
            fill_value=s.fill, compressors=_compressor(s.name),
        )
    for name, (row, dtype, chunk_rows) in FLAT_ARRAYS.items():
        root.create_array(
            name, shape=(0, *row), dtype=dtype, chunks=(chunk_rows, *row), fill_value=0,
            compressors=_compressor(name),
        )
    # Every commit flag exists from the start (pending): with many writers, blocks commit in any
    # order, and an absent state chunk stays a sign of damage (occdata.store.integrity).
    root["status/state"].with_config({"write_empty_chunks": True})[:] = np.zeros(n, dtype=np.uint8)
    root.attrs.put(attrs)


def _root_attrs(config: BuildConfig, ds: NuScenesDataset, split_names: list[str]) -> dict[str, Any]:
    first = 0
    scenes = []
    for sc in ds.scenes:
        scenes.append({
            "name": sc.name, "token": sc.token, "split": sc.split, "location": sc.location,
            "description": sc.description, "first_index": first, "num_samples": len(sc.sample_tokens),
        })
        first += len(sc.sample_tokens)
    opts = config.options
    return {
        "schema": SCHEMA_NAME,
        "schema_version": SCHEMA_VERSION,
        "n_samples": len(ds.samples),
        "camera_order": list(CAMERA_ORDER),
        "class_names": list(CLASS_NAMES),
        "class_colors": [list(c) for c in CLASS_COLORS],
        "free_label": FREE_LABEL,
        "grid": {"lower": list(GRID.lower), "upper": list(GRID.upper), "voxel_size": GRID.voxel_size,
                 "shape": list(GRID.shape), "frame": "key ego (LIDAR_TOP keyframe ego pose)",
                 "axis_order": "x, y, z"},
        "splits": split_names,
        "scenes": scenes,
        "images": {"encoding": "jpeg", "scale": opts.image_scale,
                   "reencoded": opts.image_scale != 1.0, "jpeg_quality": opts.jpeg_quality if
                   opts.image_scale != 1.0 else None},
        "depth": {"columns": ["u", "v", "depth"], "pixel_frame": "original image pixels",
                  "min_depth": opts.min_depth, "lidar_sweeps": opts.lidar_sweeps,
                  "source": "keyframe LIDAR_TOP" + (f" + up to {opts.lidar_sweeps} previous sweeps, motion-"
                                                    "compensated to each camera's timestamp" if opts.lidar_sweeps
                                                    else "")},
        "bev": {"encoding": "uint32 bit field, bit c = class c present in the column",
                "free_bit": FREE_LABEL},
        "checksum_arrays": list(checksummed_names()),
        "checksum": "crc32 of each array's per-sample C-order bytes (flat arrays: its 6 camera slices)",
        "build_identity": _identity(config, ds),
        "build_config": {"workers": config.workers, "on_error": config.on_error},
        "errors": [],
        "complete": False,
    }


STAGING_SUFFIX = ".staging"  # <store>.staging: converted blocks not yet committed
_CREATING = "occdata_creating"  # root attribute of a store whose layout is still being written (object stores)


def sample_checksums(arrays: dict[str, np.ndarray], flat: dict[str, bytes]) -> np.ndarray:
    """`(A,) uint32` crc32 per checksummed array, in `checksummed_names()` order."""
    out = []
    for name in checksummed_names():
        if name in FLAT_ARRAYS:
            out.append(zlib.crc32(flat[name]))
        else:
            out.append(zlib.crc32(np.ascontiguousarray(arrays[name]).tobytes()))
    return np.array(out, dtype=np.uint32)


def _resume_state(root: zarr.Group) -> np.ndarray:
    """The commit flags as an earlier run left them; an absent chunk is pending (it is rebuilt)."""
    arr = root["status/state"]
    rows = int(arr.chunks[0])
    out = np.zeros(arr.shape, dtype=np.uint8)
    for i0 in range(0, arr.shape[0], rows):
        try:
            out[i0 : i0 + rows] = arr[i0 : i0 + rows]
        except Exception as exc:  # noqa: BLE001 - a damaged chunk: say which file and how to recover
            key = f"status/state/{arr.metadata.encode_chunk_key((i0 // rows,))}"
            raise OccDataError(
                f"cannot resume: the commit flags of samples {i0}..{min(i0 + rows, arr.shape[0]) - 1} are unreadable "
                f"({type(exc).__name__}: {exc}); delete {key} inside the store and rerun --resume to rebuild them"
            ) from None
    return out


def _store_exists(out: str) -> bool:
    """A store is there once its layout is complete (locally: the folder, published by rename;
    on an object store: a root `zarr.json` not marked as still being created)."""
    if not is_remote(out):
        return os.path.lexists(out)
    raw = read_bytes(join(out, "zarr.json"))
    if raw is None:
        return False
    try:
        return not json.loads(raw).get("attributes", {}).get(_CREATING, False)
    except ValueError:
        return True  # not ours to overwrite: the resume checks report it


def _open_existing(config: BuildConfig, out: str, attrs: dict[str, Any]) -> zarr.Group:
    if not config.resume:
        raise OccDataError(f"store exists: {out} (pass --resume to continue it, or choose another --out)")
    try:
        root = zarr.open_group(out, mode="r+", use_consolidated=False)  # the client sees every array as it is
    except Exception as exc:  # noqa: BLE001 - any unreadable store is reported the same way
        raise OccDataError(f"cannot resume {out}: not a readable zarr store ({exc})") from None
    if root.attrs.get("schema") == SCHEMA_NAME:
        try:
            StoreReader(out)  # every array there with the schema's shape (edited zarr.json, ...)
        except OccDataError as exc:
            raise OccDataError(f"cannot resume: {exc}") from None
    if root.attrs.get("schema") != SCHEMA_NAME:
        raise OccDataError(f"cannot resume {out}: not an occdata store (no schema attribute)")
    stored = root.attrs.get("build_identity")
    if isinstance(stored, dict) and isinstance(stored.get("options"), dict):
        stored = {**stored, "options": {"lidar_sweeps": 0, **stored["options"]}}  # stores from before sweeps
    if stored != attrs["build_identity"]:
        diffs = identity_diff(stored if isinstance(stored, dict) else {}, attrs["build_identity"])
        raise OccDataError(
            f"cannot resume {out}: it was built from other inputs or options: {'; '.join(diffs)}. "
            "Rerun with the store's values, or use a new --out"
        )
    if not is_remote(out):
        for partial in Path(out).rglob("*.partial"):  # atomic-write leftovers of a killed run
            partial.unlink(missing_ok=True)
    return root


def _open_or_create(config: BuildConfig, ds: NuScenesDataset, split_names: list[str]) -> tuple[zarr.Group, str]:
    """The store to write, and its location (a local path or a URL)."""
    out = store_location(config.out)
    attrs = _root_attrs(config, ds, split_names)
    if _store_exists(out):
        return _open_existing(config, out, attrs), out
    remove_tree(sibling(out, STAGING_SUFFIX))  # left by an earlier store of that name: not ours
    tok_width = token_width(_all_tokens(ds))
    if is_remote(out):  # no rename on an object store: the root is marked until the layout is complete
        root = zarr.open_group(out, mode="w", attributes={_CREATING: True})
        _create(root, len(ds.samples), config.block_samples, attrs, tok_width)
        consolidate(out)
        return zarr.open_group(out, mode="r+", use_consolidated=False), out
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(out + ".creating")
    shutil.rmtree(tmp, ignore_errors=True)
    root = zarr.open_group(tmp, mode="w")
    _create(root, len(ds.samples), config.block_samples, attrs, tok_width)
    consolidate(str(tmp))
    tmp.rename(out)  # the store appears only once its layout is complete
    return zarr.open_group(out, mode="r+", use_consolidated=False), out

def _all_tokens(ds: NuScenesDataset) -> Iterator[str]:
    for s in ds.samples:
        yield s.token
        yield s.lidar.token
        yield from (c.token for c in s.cameras)


def build_store(config: BuildConfig, client: Any = None) -> BuildReport:
    """Build (or resume) a store. Raises `OccDataError` on bad options or, with on_error=fail,
    at the first bad sample, after committing every sample before it; `occdata.runtime.cluster.Interrupted`
    on Ctrl-C/SIGTERM. `client`: a `distributed.Client` to use (default: one for `config.workers`
    and `config.scheduler`, closed at the end)."""
    if config.block_samples < 1 or config.workers < 1:
        raise OccDataError("--workers and --block-samples must be >= 1")
    if not 0.05 <= config.options.image_scale <= 1.0:
        raise OccDataError("--image-scale must be in [0.05, 1]")
    if not 1 <= config.options.jpeg_quality <= 100:
        raise OccDataError(f"--jpeg-quality must be in [1, 100], got {config.options.jpeg_quality}")
    n_sweeps = config.options.lidar_sweeps
    ds = load_nuscenes(config.root, config.version, sweeps=n_sweeps > 0).select(config.splits or None)
    if not ds.samples:
        raise OccDataError(f"no samples selected under {config.root} (splits: {list(config.splits) or 'all'})")
    histories = [ds.lidar_history(i, n_sweeps) for i in range(len(ds.samples))]
    check_sweep_files(histories, n_sweeps)  # before anything is written
    if config.gts is not None and not Path(config.gts).is_dir():
        raise OccDataError(f"labels folder not found: {config.gts}")
    labels: list[Path | None] = [None] * len(ds.samples)
    if config.gts is not None:
        labels, ds = find_label_files(Path(config.gts), ds, config.labels_required)
    split_names = sorted({sc.split for sc in ds.scenes})
    scene_pos = {sc.token: i for i, sc in enumerate(ds.scenes)}
    scene_index = np.array([scene_pos[s.scene_token] for s in ds.samples])
    in_scene = np.array([s.index_in_scene for s in ds.samples])
    prev_index, prev_valid = temporal_indices(scene_index, in_scene)
    split_code = {name: i for i, name in enumerate(split_names)}
    with store_lock(config.out, "build"):
        try:
            if client is not None:
                return _build_locked(config, client, ds, labels, split_names, split_code, scene_index, prev_index,
                                     prev_valid, histories)
            with cluster_client(ClusterConfig(workers=config.workers, scheduler=config.scheduler)) as own:
                return _build_locked(config, own, ds, labels, split_names, split_code, scene_index, prev_index,
                                     prev_valid, histories)
        except OSError as exc:  # a full disk, a read-only folder: committed samples are kept
            where = f" ({exc.filename})" if exc.filename else ""
            raise OccDataError(
                f"cannot write the store {config.out}: {exc.strerror or exc}{where}. Everything committed so far "
                "is kept; fix the cause and rerun with --resume"
            ) from None


class _Coordinator:
    """Client side of a build run: places converted blocks in block order and hands back their
    commit jobs; records errors (skip) or stops at the first failed sample (fail)."""

    def __init__(self, root: zarr.Group, out: str, staging: str, spans: list[tuple[int, int, int]],
                 todo: set[int], on_error: str) -> None:
        self.root, self.out, self.staging, self.spans, self.todo = root, out, staging, spans, todo
        self.on_error = on_error
        self.summaries: dict[int, BlockSummary] = {}
        self.next = 0  # position in spans of the next block to place
        self.failure: tuple[int, str, str] | None = None
        self.errors: list[dict[str, Any]] = []
        self.footprints: dict[str, dict[int, tuple[int, int] | None]] = {}
        self.placers: dict[str, Placer] = {}
        for off_name, flat_name in FLAT_OF_OFFSETS.items():
            chunk = FLAT_ARRAYS[flat_name][2]
            offsets = root[off_name][:] if len(todo) < len(spans) else None
            fp = {b: flat_footprint(offsets[i0:i1], chunk) for b, i0, i1 in spans if b not in todo} if (
                offsets is not None) else {}
            self.footprints[flat_name] = fp
            self.placers[flat_name] = Placer(chunk, [f for f in fp.values() if f is not None])

    def keep(self, job: ConvertJob | CommitJob) -> bool:
        """After a failure under --on-error fail, blocks after the failed one are not converted."""
        return not (self.failure is not None and isinstance(job, ConvertJob) and job.i0 > self.failure[0])

    def add(self, summary: BlockSummary) -> list[CommitJob]:
        self.summaries[summary.block] = summary
        if self.on_error == "fail" and summary.errors:
            first = min(summary.errors)
            if self.failure is None or first[0] < self.failure[0]:
                self.failure = first
        jobs: list[CommitJob] = []
        while self.next < len(self.spans):
            b, i0, i1 = self.spans[self.next]
            if b not in self.todo:
                for name, placer in self.placers.items():
                    placer.skip(self.footprints[name].get(b))
                self.next += 1
                continue
            s = self.summaries.get(b)
            if s is None or (self.failure is not None and i0 > self.failure[0]):
                break
            jobs.append(self._place(s, i0, i1))
            self.next += 1
        return jobs

    def _place(self, s: BlockSummary, i0: int, i1: int) -> CommitJob:
        starts = {name: placer.place(s.rows[name]) for name, placer in self.placers.items()}
        grown = False
        for name, placer in self.placers.items():  # the client alone writes metadata
            arr = open_flat(self.out, name)
            if arr.shape[0] < placer.high:  # grow by doubling: few metadata rewrites (trimmed at the end)
                step = max(placer.high, 2 * arr.shape[0], 16 * arr.chunks[0])
                arr.resize((_align(step, arr.chunks[0]), *arr.shape[1:]))
                grown = True
        if grown:
            consolidate(self.out)
        until = i1
        if self.failure is not None and i0 <= self.failure[0] < i1:
            until = self.failure[0]
        elif s.errors:  # skip: the errors are recorded before the block's state says "error"
            self.errors += [{"index": int(i), "token": t, "reason": r} for i, t, r in s.errors]
            self.root.attrs["errors"] = sorted(self.errors, key=lambda e: e["index"])
        return CommitJob(self.out, self.staging, s.block, i0, i1, starts, until)


def _align(n: int, chunk: int) -> int:
    return -(-n // chunk) * chunk


def consolidate(out: str) -> None:
    """Rewrite the consolidated metadata (one read gives every array's metadata, on S3 too)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zarr: consolidated metadata is not (yet) in the v3 spec
        zarr.consolidate_metadata(out)


def _set_flat_length(out: str, name: str, rows: int) -> None:
    """The final length of a flat array (grown by steps during the build); a shrink deletes nothing
    (no chunk lies beyond the placed blocks), so it costs one metadata write, not a listing."""
    arr = open_flat(out, name)
    if arr.shape[0] == rows:
        return
    try:
        sync(arr._async_array.resize((rows, *arr.shape[1:]), delete_outside_chunks=False))
    except TypeError:  # a zarr without that option
        arr.resize((rows, *arr.shape[1:]))


def _reset_blocks(root: zarr.Group, state: np.ndarray, spans: list[tuple[int, int, int]], todo: set[int],
                  every: bool) -> None:
    """Blocks to (re)build are pending again before any of their data moves; their old errors go.
    `every` (a resumed store): also write the flags that are pending already, so that a store from
    before issue 24 (no state chunk for its pending tail) has every state chunk from now on."""
    arr = root["status/state"].with_config({"write_empty_chunks": True})
    for b, i0, i1 in spans:
        if b in todo and (every or (state[i0:i1] != STATE_PENDING).any()):
            arr[i0:i1] = np.zeros(i1 - i0, dtype=np.uint8)
    if root.attrs.get("errors"):
        root.attrs["errors"] = []


def _build_locked(config: BuildConfig, client: Any, ds: NuScenesDataset, labels: list[Path | None],
                  split_names: list[str], split_code: dict[str, int], scene_index: np.ndarray,
                  prev_index: np.ndarray, prev_valid: np.ndarray,
                  histories: list[tuple[LidarRecord, ...]]) -> BuildReport:
    resumed = _store_exists(store_location(config.out))
    root, out = _open_or_create(config, ds, split_names)
    staging = sibling(out, STAGING_SUFFIX)
    state = _resume_state(root)
    n, bs = len(ds.samples), config.block_samples
    spans = [(b, i0, min(i0 + bs, n)) for b, i0 in enumerate(range(0, n, bs))]
    todo = {b for b, i0, i1 in spans if (state[i0:i1] != STATE_DONE).any()}
    if todo and root.attrs.get("complete"):
        root.attrs["complete"] = False  # until this run has committed them again
    _reset_blocks(root, state, spans, todo, every=resumed)
    coord = _Coordinator(root, out, staging, spans, todo, config.on_error)
    tok_width = int(root["sample/token"].shape[-1])

    def convert_job(b: int, i0: int, i1: int) -> ConvertJob:
        args = []
        for i in range(i0, i1):
            s = ds.samples[i]
            static = static_arrays(s, int(scene_index[i]), split_code[ds.scenes[scene_index[i]].split],
                                   prev_index[i], prev_valid[i], tok_width)
            args.append((i, s, static, labels[i], config.options, histories[i]))
        return ConvertJob(out, staging, b, i0, i1, tuple(args))

    jobs: list[ConvertJob | CommitJob] = []
    for b, i0, i1 in spans:
        if b not in todo:
            continue
        staged = staged_summary(staging, b)
        if staged is not None and not staged.errors:  # converted by an interrupted run: commit it
            jobs += coord.add(staged)
        else:
            jobs.append(convert_job(b, i0, i1))
    converted = [0]

    def on_result(job: ConvertJob | CommitJob, result: Any) -> list[ConvertJob | CommitJob]:
        if isinstance(job, ConvertJob):  # samples that needed work (a block's done ones are redone with it)
            converted[0] += int((state[job.i0 : job.i1] != STATE_DONE).sum())
            return list(coord.add(result))
        return []

    run_tasks(client, run_job, jobs, desc="build", progress=config.progress, on_result=on_result, keep=coord.keep,
              units=lambda j: j.i1 - j.i0 if isinstance(j, ConvertJob) else 0)
    if coord.failure is not None:
        i, token, reason = coord.failure
        raise OccDataError(
            f"sample {i} ({token}) failed: {reason}. Everything before it is committed; fix the input and rerun "
            "with --resume (or use --on-error skip)."
        )
    return _finish(config, root, out, staging, ds, converted[0], {n: p.high for n, p in coord.placers.items()})


def _committed_end(root: zarr.Group, flat_name: str) -> int:
    """The end of the last range that a committed sample uses in a flat array (chunk-aligned)."""
    off_name = next(o for o, f in FLAT_OF_OFFSETS.items() if f == flat_name)
    off = root[off_name][:]
    used = off[..., 1] > 0
    end = int((off[..., 0] + off[..., 1])[used].max()) if used.any() else 0
    return _align(end, FLAT_ARRAYS[flat_name][2])


def _finish(config: BuildConfig, root: zarr.Group, out: str, staging: str, ds: NuScenesDataset,
            processed: int, high: dict[str, int]) -> BuildReport:
    """The final commit (idempotent): completeness, the run's options, staging removed."""
    final_state = root["status/state"][:]
    complete = bool((final_state != STATE_PENDING).all())
    if complete:
        remove_tree(staging)
        for name, rows in high.items():
            _set_flat_length(out, name, max(rows, _committed_end(root, name)))
    root.attrs.update({"complete": complete, "build_config": {"workers": config.workers, "on_error": config.on_error}})
    consolidate(out)
    return BuildReport(
        store=Path(out) if not is_remote(out) else out,  # type: ignore[arg-type]
        n_samples=len(ds.samples),
        n_done=int((final_state == STATE_DONE).sum()),
        n_errors=int((final_state == STATE_ERROR).sum()),
        n_labelled=int(root["labels/present"][:].sum()),
        processed_now=processed,
        warnings=ds.warnings,
    )

def check_sweep_files(histories: list[tuple[LidarRecord, ...]], n_sweeps: int) -> None:
    """Raise one `OccDataError` line if any sweep file that `--lidar-sweeps` needs is not a file:
    it names the first missing one and how many of the needed files were found."""
    needed = list(dict.fromkeys(sw for h in histories for sw in h))  # samples share sweeps
    missing = [sw for sw in needed if not sw.path.is_file()]
    if missing:
        first = missing[0]
        raise OccDataError(
            f"--lidar-sweeps {n_sweeps}: missing sweep file {first.path} (sample_data {first.token!r}); "
            f"{len(needed) - len(missing)} of the {len(needed)} sweep files needed were found. A keyframe-only "
            "download has no sweeps/ folder: add the sweeps, or use --lidar-sweeps 0"
        )


def label_layouts(scene_name: str, token: str) -> tuple[str, str]:
    """The two accepted places of a sample's labels, relative to `gts`: Occ3D-nuScenes nests them
    by scene name, the flat layout (e.g. a single downloaded example) does not."""
    return f"{scene_name}/{token}/labels.npz", f"{token}/labels.npz"


def find_label_files(
    gts: Path, ds: NuScenesDataset, required: bool
) -> tuple[list[Path | None], NuScenesDataset]:
    """Per sample, its `labels.npz` under `gts` (nested `<scene>/<token>/` first, then flat
    `<token>/`), or None. Scene names and tokens come from the tables: a label path that would leave
    `gts` marks that sample with a problem (the sample fails, naming the row). With `required`, no
    match for any sample is an error that shows the expected layout and one expected path.
    """
    found: list[Path | None] = []
    samples = []
    for s in ds.samples:
        where = f"scene {s.scene_name!r} / sample {s.token!r} (labels path under --gts)"
        path: Path | None = None
        try:
            candidates = [confined_path(gts, rel, where) for rel in label_layouts(s.scene_name, s.token)]
            path = next((c for c in candidates if os.path.lexists(c)), None)
        except OccDataError as exc:
            s = dataclasses.replace(s, problem=s.problem or str(exc))
        found.append(path)
        samples.append(s)
    if required and ds.samples and not any(found):
        s = ds.samples[0]
        nested, flat = label_layouts(s.scene_name, s.token)
        raise OccDataError(
            f"no label file under {gts} matches any of the {len(ds.samples)} samples; expected "
            f"{gts}/<scene name>/<sample token>/labels.npz or {gts}/<sample token>/labels.npz, "
            f"e.g. {gts / nested} (check --gts; leave it out for samples without labels, e.g. the test split)"
        )
    if any(s.problem for s in samples):
        ds = dataclasses.replace(ds, samples=tuple(samples))
    return found, ds
