"""`occdata build`: a nuScenes-format tree (+ Occ3D labels) -> one chunked zarr store.

Workers convert samples; the main process is the only writer. It writes whole blocks of samples
(one shard per block for the big arrays), then the per-sample checksums, then the state flags:
a sample is complete only once its state says so. `--resume` continues after the last committed
sample and gives a store identical to an uninterrupted build.
"""

from __future__ import annotations

import collections
import dataclasses
import multiprocessing as mp
import os
import shutil
import signal
import threading
import zlib
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zarr
from tqdm import tqdm
from zarr.codecs import ZstdCodec

from occdata.constants import CAMERA_ORDER, CLASS_COLORS, CLASS_NAMES, FREE_LABEL, GRID
from occdata.errors import OccDataError
from occdata.nuscenes import LidarRecord, NuScenesDataset, load_nuscenes
from occdata.nuscenes.reader import confined_path
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
from occdata.store.lock import store_lock
from occdata.store.reader import StoreReader
from occdata.store.sample import SampleOptions, SampleResult, process_sample, static_arrays, temporal_indices

__all__ = ["BuildConfig", "BuildReport", "build_store", "check_sweep_files", "find_label_files", "identity_diff",
           "label_layouts", "sample_checksums"]


@dataclass(frozen=True)
class BuildConfig:
    root: Path
    out: Path
    version: str | None = None
    gts: Path | None = None
    # With labels_required (an explicit --gts), a labels folder in which no sample finds its file
    # is an error (a wrong folder would give a silently unlabelled store); off for the default
    # <root>/gts, which may legitimately hold no labels for the selected split (test).
    labels_required: bool = True
    splits: tuple[str, ...] = ()
    workers: int = 1
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
    root.attrs.update(attrs)


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


def sample_checksums(arrays: dict[str, np.ndarray], flat: dict[str, bytes]) -> np.ndarray:
    """`(A,) uint32` crc32 per checksummed array, in `checksummed_names()` order."""
    out = []
    for name in checksummed_names():
        if name in FLAT_ARRAYS:
            out.append(zlib.crc32(flat[name]))
        else:
            out.append(zlib.crc32(np.ascontiguousarray(arrays[name]).tobytes()))
    return np.array(out, dtype=np.uint32)


class _Writer:
    """Commits runs of consecutive sample results to the store (the single writer)."""

    def __init__(self, root: zarr.Group) -> None:
        self.root = root
        self.arrays = {s.name: root[s.name] for s in PER_SAMPLE}
        self.flat = {name: root[name] for name in FLAT_ARRAYS}
        self.initial_state = _resume_state(root)  # what an earlier (killed) run committed
        self.cursor = {name: 0 for name in FLAT_ARRAYS}
        committed = self.initial_state != STATE_PENDING
        for off_name, flat_name in FLAT_OF_OFFSETS.items():
            if committed.any():
                off = self.arrays[off_name][:][committed]
                self.cursor[flat_name] = int((off[..., 0] + off[..., 1]).max(initial=0))
        self.fill = {s.name: np.full(self.arrays[s.name].shape[1:], s.fill, dtype=s.dtype) for s in PER_SAMPLE}

    def commit(self, results: list[SampleResult]) -> None:
        if not results:
            return
        i0, i1 = results[0].index, results[-1].index + 1
        assert [r.index for r in results] == list(range(i0, i1))
        # Offsets and payloads of the ragged arrays, sample after sample.
        per_sample_flat: list[dict[str, bytes]] = []
        offsets = {name: np.zeros((len(results), 6, 2), dtype=np.int64) for name in FLAT_OF_OFFSETS}
        rows_so_far = dict(self.cursor)
        for k, r in enumerate(results):
            parts = {"images/jpeg": list(r.jpeg), "depth/uvd": [u.tobytes() for u in r.uvd]}
            mine = {}
            for off_name, flat_name in FLAT_OF_OFFSETS.items():
                row_bytes = _row_bytes(flat_name)
                for c, part in enumerate(parts[flat_name]):
                    offsets[off_name][k, c] = (rows_so_far[flat_name], len(part) // row_bytes)
                    rows_so_far[flat_name] += len(part) // row_bytes
                if not parts[flat_name]:  # failed sample: empty ranges at the cursor
                    offsets[off_name][k, :, 0] = rows_so_far[flat_name]
                mine[flat_name] = b"".join(parts[flat_name])
            per_sample_flat.append(mine)
        # 1. ragged payloads
        for flat_name in FLAT_ARRAYS:
            blob = b"".join(m[flat_name] for m in per_sample_flat)
            row_shape, dtype, _ = FLAT_ARRAYS[flat_name]
            data = np.frombuffer(blob, dtype=dtype).reshape((-1, *row_shape))
            start = self.cursor[flat_name]
            end = start + len(data)
            arr = self.flat[flat_name]
            if arr.shape[0] != end:
                arr.resize((end, *row_shape))
            if len(data):
                arr[start:end] = data
            self.cursor[flat_name] = end
        # 2. per-sample arrays (failed samples: static arrays only, the rest stays at fill)
        block: dict[str, np.ndarray] = {}
        for s in PER_SAMPLE:
            if s.name.startswith("status/"):
                continue
            if s.name in offsets:
                block[s.name] = offsets[s.name]
            else:
                stacked = np.stack([r.arrays.get(s.name, self.fill[s.name]) for r in results])
                block[s.name] = stacked.astype(s.dtype, copy=False)
            self.arrays[s.name][i0:i1] = block[s.name]
        # 3. checksums, then errors, then the state flags (the commit point)
        sums = np.stack([
            sample_checksums({n: block[n][k] for n in block}, per_sample_flat[k]) for k in range(len(results))
        ])
        self.arrays["status/checksum"][i0:i1] = sums
        failed = [r for r in results if r.error]
        old_errors = self.root.attrs.get("errors", [])
        if failed or any(i0 <= e["index"] < i1 for e in old_errors):  # a retried sample may now succeed
            errors = [e for e in old_errors if not i0 <= e["index"] < i1]
            errors += [{"index": r.index, "token": r.token, "reason": r.error} for r in failed]
            self.root.attrs["errors"] = sorted(errors, key=lambda e: e["index"])
        self.arrays["status/state"][i0:i1] = np.array(
            [STATE_ERROR if r.error else STATE_DONE for r in results], dtype=np.uint8
        )

    def finish(self) -> None:
        for flat_name, arr in self.flat.items():
            if arr.shape[0] != self.cursor[flat_name]:
                arr.resize((self.cursor[flat_name], *arr.shape[1:]))


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


def _row_bytes(flat_name: str) -> int:
    row_shape, dtype, _ = FLAT_ARRAYS[flat_name]
    return int(np.dtype(dtype).itemsize * int(np.prod(row_shape, dtype=np.int64)))


def _open_or_create(config: BuildConfig, ds: NuScenesDataset, split_names: list[str]) -> zarr.Group:
    out = Path(config.out)
    attrs = _root_attrs(config, ds, split_names)
    if out.exists():
        if not config.resume:
            raise OccDataError(f"store exists: {out} (pass --resume to continue it, or choose another --out)")
        try:
            root = zarr.open_group(out, mode="r+")
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
        for partial in out.rglob("*.partial"):  # atomic-write leftovers of a killed run
            partial.unlink(missing_ok=True)
        return root
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".creating")
    shutil.rmtree(tmp, ignore_errors=True)
    root = zarr.open_group(tmp, mode="w")
    _create(root, len(ds.samples), config.block_samples, attrs, token_width(_all_tokens(ds)))
    tmp.rename(out)  # the store appears only once its layout is complete
    return zarr.open_group(out, mode="r+")


def _all_tokens(ds: NuScenesDataset) -> Iterator[str]:
    for s in ds.samples:
        yield s.token
        yield s.lidar.token
        yield from (c.token for c in s.cameras)


def _work(args: tuple[Any, ...]) -> SampleResult:
    return process_sample(*args)


def build_store(config: BuildConfig) -> BuildReport:
    """Build (or resume) a store. Raises `OccDataError` on bad options or, with on_error=fail,
    at the first bad sample, after committing every sample before it."""
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
            return _build_locked(config, ds, labels, split_names, split_code, scene_index, prev_index, prev_valid,
                                 histories)
        except OSError as exc:  # a full disk, a read-only folder: committed samples are kept
            where = f" ({exc.filename})" if exc.filename else ""
            raise OccDataError(
                f"cannot write the store {config.out}: {exc.strerror or exc}{where}. Everything committed so far "
                "is kept; fix the cause and rerun with --resume"
            ) from None


def _build_locked(config: BuildConfig, ds: NuScenesDataset, labels: list[Path | None], split_names: list[str],
                  split_code: dict[str, int], scene_index: np.ndarray, prev_index: np.ndarray,
                  prev_valid: np.ndarray, histories: list[tuple[LidarRecord, ...]]) -> BuildReport:
    root = _open_or_create(config, ds, split_names)
    writer = _Writer(root)
    # Pending samples, and those that failed before (their input may have been fixed since).
    pending = np.flatnonzero(writer.initial_state != STATE_DONE)
    if len(pending) and root.attrs.get("complete"):
        root.attrs["complete"] = False  # until this run has committed them again
    tok_width = int(root["sample/token"].shape[-1])

    def tasks() -> Iterator[tuple[Any, ...]]:
        for i in pending:
            s = ds.samples[i]
            static = static_arrays(
                s, int(scene_index[i]), split_code[ds.scenes[scene_index[i]].split], prev_index[i], prev_valid[i],
                tok_width,
            )
            yield (int(i), s, static, labels[int(i)], config.options, histories[int(i)])

    block = config.block_samples
    run: list[SampleResult] = []
    processed = 0
    bar = tqdm(total=len(pending), desc="build", unit="sample", disable=not config.progress, dynamic_ncols=True)
    stop = _DeferredInterrupt()
    try:
        with stop:
            for result in _results(tasks(), config.workers, stop):
                if result.error and config.on_error == "fail":
                    writer.commit(run)
                    writer.finish()
                    raise OccDataError(
                        f"sample {result.index} ({result.token}) failed: {result.error}. "
                        f"Everything before it is committed; fix the input and rerun with --resume "
                        f"(or use --on-error skip)."
                    )
                if run and result.index != run[-1].index + 1:
                    writer.commit(run)
                    run = []
                run.append(result)
                processed += 1
                bar.update(1)
                if (result.index + 1) % block == 0 or result.index == len(ds.samples) - 1:
                    writer.commit(run)
                    run = []
                if stop.hit:
                    break
            writer.commit(run)  # results already received are kept, also on Ctrl-C
            writer.finish()
    finally:
        bar.close()
    if stop.hit:
        raise KeyboardInterrupt
    final_state = root["status/state"][:]
    complete = bool((final_state != STATE_PENDING).all())
    root.attrs["complete"] = complete
    root.attrs["build_config"] = {"workers": config.workers, "on_error": config.on_error}
    return BuildReport(
        store=Path(config.out),
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


class _DeferredInterrupt:
    """Ctrl-C sets a flag that the build loop checks after each sample (a commit is never cut in
    half); a second Ctrl-C interrupts at once. Only in the main thread (signals live there)."""

    def __init__(self) -> None:
        self.hit = False
        self._prev: Any = None

    def _handler(self, signum: int, frame: Any) -> None:
        self.hit = True
        signal.signal(signal.SIGINT, self._prev)

    def __enter__(self) -> _DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._prev = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._prev is not None:
            signal.signal(signal.SIGINT, self._prev)
            self._prev = None


def _ignore_sigint() -> None:
    """Worker initializer: Ctrl-C in a terminal reaches the whole process group; only the main
    process acts on it (no KeyboardInterrupt tracebacks from workers, no half-dead pool)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _results(tasks: Iterator[tuple[Any, ...]], workers: int, stop: _DeferredInterrupt) -> Iterator[SampleResult]:
    """Results in task order; at most a few tasks in flight per worker, so memory stays bounded."""
    if workers == 1:
        for t in tasks:
            yield _work(t)
            if stop.hit:
                return
        return
    window: collections.deque[Future[SampleResult]] = collections.deque()
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_ignore_sigint)
    try:
        for t in tasks:
            if stop.hit:
                return
            window.append(pool.submit(_work, t))
            if len(window) >= 3 * workers:
                yield window.popleft().result()
        while window and not stop.hit:
            yield window.popleft().result()
    finally:
        # Interrupted or failed: cancel what no worker has started; the few tasks in flight finish
        # (workers ignore SIGINT) and the pool shuts down cleanly. Terminating workers instead can
        # hang the shutdown (a killed worker may hold the call queue's lock), and so can
        # `concurrent.futures.wait` on futures that the shutdown cancels (never counted as done).
        pool.shutdown(wait=True, cancel_futures=True)

