"""Read-only access to a store: per-sample arrays, images, depth points (no torch)."""

from __future__ import annotations

import asyncio
import json
import urllib.parse
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import zarr
from zarr.core.buffer import default_buffer_prototype
from zarr.core.metadata.v3 import ArrayV3Metadata
from zarr.core.sync import sync

from occdata.errors import OccDataError
from occdata.formats.gridspec import GridSpec
from occdata.store.integrity import CorruptStoreError, StoreIntegrity
from occdata.store.labelgrid import store_grid
from occdata.store.layout import (
    FLAT_ARRAYS,
    MIN_TOKEN_BYTES,
    READABLE_SCHEMA_VERSIONS,
    SCHEMA_NAME,
    STATE_DONE,
    STATE_ERROR,
    STATE_PENDING,
    TOKEN_ARRAYS,
    camera_count,
    checksummed_names,
    grid_shape,
    has_flow,
    per_sample,
    token_str,
)
from occdata.store.pack import PACK_ATTR, PACK_GROUP, pack_names, packed_crc

__all__ = ["StoreReader", "open_store", "store_location"]


def store_location(path: str | Path) -> str:
    """A store path or fsspec URL as zarr should get it: `file://` URLs (and the `file:/x` that
    some tools make of them) become plain local paths, so local stores are written with ordinary
    file operations; other URLs (s3://, gs://, memory://, ...) are passed on unchanged."""
    text = str(path)
    if text.startswith("file:"):
        parsed = urllib.parse.urlparse(text)
        if parsed.netloc not in ("", "localhost"):
            raise OccDataError(f"cannot open {text}: only local file:// URLs are supported")
        return urllib.parse.unquote(parsed.path)
    return text


class StoreReader:
    """A thin reader over one store. `root` may be a local path or an fsspec URL.

    Opening costs a bounded number of requests, whatever the sample count: the root `zarr.json` with
    the consolidated metadata (every array's metadata), with `check_metadata` each array's own
    `zarr.json` fetched concurrently and compared with it (an edited or damaged one is seen, and the
    store is then opened array by array, which names it), and with `packed` one request per small array
    read (`small`: the copies the build's final commit packed, occdata.store.pack). Without `packed`
    (checks, verify, tools) `small` reads the block chunks, where damage shows. Stores without
    consolidated metadata or packed copies (older versions, an interrupted build) open array by array
    and read the block chunks.
    """

    def __init__(self, root: str | Path, check_metadata: bool = True, packed: bool = False) -> None:
        self.path = store_location(root)
        self.group, self.consolidated = _open_group(self.path)
        if self.consolidated and check_metadata and not _array_files_agree(self.group):
            self.group, self.consolidated = _open_group(self.path, consolidated=False)
        attrs = dict(self.group.attrs)
        if attrs.get("schema") != SCHEMA_NAME:
            raise OccDataError(f"not an occdata store: {self.path} (no schema attribute)")
        if attrs.get("schema_version") not in READABLE_SCHEMA_VERSIONS:
            raise OccDataError(
                f"store {self.path} has schema version {attrs.get('schema_version')}, this package reads "
                f"{', '.join(map(str, READABLE_SCHEMA_VERSIONS))}; rebuild it with this version of occdata"
            )
        self.attrs: dict[str, Any] = attrs
        self.has_flow: bool = has_flow(attrs)  # `labels/flow` (schema version 3)
        self.grid: GridSpec = store_grid(attrs)  # the label grid (Occ3D's unless attrs["grid"] names another)
        self.grid_shape: tuple[int, int, int] = grid_shape(attrs)
        self.n_cams: int = camera_count(attrs)  # the cameras of the store's rig (attrs camera_order)
        if self.grid.shape != self.grid_shape:
            raise OccDataError(f"store {self.path}: attribute grid has shape {list(self.grid_shape)}, but its "
                               f"range and voxel size make {list(self.grid.shape)}; the metadata was edited")
        self.n_samples: int = self._check_layout()
        self._cache: dict[str, np.ndarray] = {}
        pack = attrs.get(PACK_ATTR) if packed else None
        self.pack_generation: str | None = pack.get("generation") if isinstance(pack, dict) else None
        if packed and self.pack_generation is None and attrs.get("complete"):
            warnings.warn(f"store {self.path} has no packed small arrays (built before occdata packed them, or "
                          "changed since): the loader reads them block by block, one request per block and array; "
                          "`occdata build ... --resume` with this version packs them", UserWarning, stacklevel=3)
        self.integrity = StoreIntegrity(self.group, attrs, packed=self._known)

    def _check_layout(self) -> int:
        """Every array exists with the schema's shape and dtype, and agrees on the sample count.

        Returns the sample count. An edited or damaged `zarr.json` gives one line naming the array.
        """
        n = self.attrs.get("n_samples")
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            raise OccDataError(f"store {self.path}: attribute n_samples is {n!r}, not a sample count")
        n_check = len(checksummed_names(self.has_flow))
        expected = {s.name: ((n, n_check) if s.name == "status/checksum" else (n, *s.shape), s.dtype)
                    for s in per_sample(self.has_flow, self.grid_shape, self.n_cams)}
        for name, (row, dtype, _) in FLAT_ARRAYS.items():
            expected[name] = ((None, *row), dtype)
        # Token arrays are as wide as the store's longest token (>= 32 bytes), the same for all three.
        try:
            width = int(self.group["sample/token"].shape[-1])
        except Exception:  # noqa: BLE001 - reported below as a missing/unreadable array
            width = MIN_TOKEN_BYTES
        if width >= MIN_TOKEN_BYTES:
            for name in TOKEN_ARRAYS:
                shape, dtype = expected[name]
                expected[name] = ((*shape[:-1], width), dtype)
        for name, (shape, dtype) in expected.items():
            try:
                arr = self.group[name]
            except Exception as exc:  # noqa: BLE001 - missing array, invalid zarr.json, ...
                raise OccDataError(
                    f"store {self.path}: array {name} is missing or its zarr.json is unreadable "
                    f"({type(exc).__name__})"
                ) from None
            got = tuple(arr.shape)
            if str(arr.dtype) != dtype or len(got) != len(shape) or any(
                e is not None and g != e for g, e in zip(got, shape, strict=True)
            ):
                want = tuple("*" if e is None else e for e in shape)
                raise OccDataError(
                    f"store {self.path}: array {name} has shape {got} {arr.dtype}, the schema (n_samples={n}) "
                    f"says {want} {dtype}; the store metadata was edited or damaged"
                )
        return n

    def array(self, name: str) -> zarr.Array:
        return self.group[name]

    def small(self, name: str) -> np.ndarray:
        """A whole small per-sample array, read once and cached (state, offsets, tokens, poses): its
        packed copy (one request) when current, else every block chunk.

        Checked: a chunk that went missing under a committed sample raises `CorruptStoreError`.
        """
        if name not in self._cache:
            packed = self._packed(name)
            if packed is not None:
                self._cache[name] = packed
            elif name == "status/state":
                self._cache[name] = self.integrity.read_state()
            else:
                state = self.small("status/state")
                try:
                    data = np.asarray(self.group[name][:])
                except Exception as exc:  # noqa: BLE001 - codec errors surface as many types
                    raise CorruptStoreError(f"store array {name} is unreadable ({type(exc).__name__}: {exc})") \
                        from None
                self.integrity.check_present(name, state)
                self._cache[name] = data
        return self._cache[name]

    def small_many(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """`small(name)` for each name; current packed copies are fetched concurrently (one round trip)."""
        arrays = {n: self._pack_array(n) for n in names if n not in self._cache}
        todo = {n: a for n, a in arrays.items() if a is not None}
        if todo:
            async def fetch() -> list:  # runs on zarr's loop: no sync zarr call in here
                return await asyncio.gather(*(a._async_array.getitem(...) for a in todo.values()),
                                            return_exceptions=True)

            for name, data in zip(todo, sync(fetch()), strict=True):
                if not isinstance(data, BaseException) and self._pack_intact(name, np.asarray(data)):
                    self._cache[name] = np.asarray(data)
        return {n: self.small(n) for n in names}

    def read_ranges(self, ranges: Sequence[tuple[str, int, int]]) -> list[np.ndarray]:
        """`array[start:stop]` for each `(name, start, stop)`, fetched concurrently: one round trip on an
        object store, not one per array (a block's images, depth and four label arrays took six). The
        first error is raised as the sequential reads would raise it."""
        arrays = [self.group[name] for name, _, _ in ranges]

        async def fetch() -> list:  # runs on zarr's loop: no sync zarr call in here
            return await asyncio.gather(*(a._async_array.getitem(slice(start, stop))
                                          for a, (_, start, stop) in zip(arrays, ranges, strict=True)))

        return [np.asarray(data) for data in sync(fetch())]

    def preload(self, arrays: dict[str, np.ndarray]) -> None:
        """Take small arrays another process already read (a loader worker: shared memory), unread."""
        self._cache.update(arrays)

    def _known(self, name: str) -> np.ndarray | None:
        """A small array without reading its chunks: cached, or its current packed copy; else None."""
        return self._cache.get(name) if name in self._cache else self._packed(name)

    def _packed(self, name: str) -> np.ndarray | None:
        """The packed copy of small array `name` if it is current and intact, else None (read the chunks)."""
        arr = self._pack_array(name)
        if arr is None:
            return None
        try:
            data = np.asarray(arr[...])
        except Exception:  # noqa: BLE001 - an unreadable copy: the chunks are the truth
            return None
        return data if self._pack_intact(name, data) else None

    def _pack_array(self, name: str) -> zarr.Array | None:
        """`pack/<name>` when it is the current generation with the array's shape and dtype, else None."""
        if self.pack_generation is None or name not in pack_names(self.attrs):
            return None
        try:
            arr = self.group[f"{PACK_GROUP}/{name}"]
            want = self.group[name]
        except Exception:  # noqa: BLE001 - a missing copy: the chunks are the truth
            return None
        if arr.attrs.get("generation") != self.pack_generation or arr.shape != want.shape or arr.dtype != want.dtype:
            return None
        return arr

    def _pack_intact(self, name: str, data: np.ndarray) -> bool:
        if packed_crc(data) == self.group[f"{PACK_GROUP}/{name}"].attrs.get("crc32"):
            return True
        warnings.warn(f"store {self.path}: the packed copy of {name} is damaged (crc32); reading its chunks",
                      RuntimeWarning, stacklevel=4)
        return False

    @property
    def state(self) -> np.ndarray:
        """`(N,) uint8` commit flags (0 pending, 1 done, 2 error), checked for missing chunks."""
        return self.small("status/state")

    def require_done(self, index: int) -> None:
        """One clear line for a sample that cannot be read: out of range, failed, or not built yet."""
        self._check_index(index)
        st = int(self.state[index])
        if st == STATE_DONE:
            return
        token = self.token(index)
        if st == STATE_ERROR:
            reason = next((e["reason"] for e in self.attrs.get("errors", []) if e.get("index") == index),
                          "reason not recorded")
            raise OccDataError(f"sample {index} ({token}) failed to build: {reason}")
        if st == STATE_PENDING:
            raise OccDataError(
                f"sample {index} ({token}) is pending: the build has not reached it yet "
                "(finish it with `occdata build ... --resume`)"
            )
        raise CorruptStoreError(f"corrupt store: sample {index} ({token}) has an unknown state {st}")

    def done_indices(self) -> np.ndarray:
        return np.flatnonzero(self.state == STATE_DONE)

    def split_indices(self, split: str | Sequence[str] | None, labelled: bool | None = None) -> np.ndarray:
        """Store indices `(n,) int64`, ascending, of the built (committed) samples of `split` (a name, several
        names, or None = every split); `labelled` True/False keeps only samples with/without Occ3D labels.

        An unknown split name is one `OccDataError` line naming the store's splits. This is the one
        definition of "the samples of a split" (loader, prediction, evaluation, class counts)."""
        keep = self.state == STATE_DONE
        if split is not None:
            wanted = [split] if isinstance(split, str) else list(split)
            names = list(self.attrs.get("splits", []))
            unknown = [s for s in wanted if s not in names]
            if unknown:
                raise OccDataError(f"split {unknown[0]!r} is not in store {self.path}: unknown split (the store "
                                   f"has {names}; a store's splits are set when it is built: occdata build "
                                   "--split-file / --unlisted-split)")
            keep &= np.isin(self.small("sample/split"), [names.index(s) for s in wanted])
        if labelled is not None:
            keep &= self.small("labels/present").astype(bool) == labelled
        return np.flatnonzero(keep)

    def token(self, index: int) -> str:
        return token_str(self.small("sample/token")[index])

    def sample_arrays(self, index: int, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
        """Per-sample arrays (no sample axis) for one sample; all of the store's arrays by default."""
        self._check_index(index)
        names = names or tuple(s.name for s in per_sample(self.has_flow, self.grid_shape, self.n_cams))
        out = {}
        committed = self.state[index] != STATE_PENDING
        checked = set(checksummed_names(self.has_flow))
        for name in names:
            try:
                out[name] = np.asarray(self.group[name][index])
            except Exception as exc:  # noqa: BLE001 - codec errors surface as many types
                raise CorruptStoreError(
                    f"corrupt store data in {name} for sample {index} ({self.token(index)}): {exc}"
                ) from None
            if committed and name in checked:  # a missing chunk reads as fill: the checksum tells
                self.integrity.check_rows(name, [index], [out[name]])
        return out

    def _flat_slice(self, flat: str, offsets_name: str, index: int) -> list[np.ndarray]:
        off = self.small(offsets_name)[index]
        if not off[:, 1].any():  # a failed sample: empty ranges
            return [self.group[flat][0:0] for _ in off]
        lo = int(off[:, 0].min())
        hi = int((off[:, 0] + off[:, 1]).max())
        try:
            data = np.asarray(self.group[flat][lo:hi])
        except Exception as exc:  # noqa: BLE001
            where = f"{flat} for sample {index} ({self.token(index)})"
            raise CorruptStoreError(f"corrupt store data in {where}: {exc}") from None
        parts = [data[int(s) - lo : int(s) - lo + int(n)] for s, n in off]
        if self.state[index] != STATE_PENDING:
            self.integrity.check_rows(flat, [index], [b"".join(p.tobytes() for p in parts)])
        return parts

    def jpeg_bytes(self, index: int) -> list[bytes]:
        """The 6 stored JPEG streams of a sample, in camera order."""
        self._check_index(index)
        return [a.tobytes() for a in self._flat_slice("images/jpeg", "images/offsets", index)]

    def images(self, index: int, reduce: int = 1) -> list[np.ndarray]:
        """Decoded RGB images `(H, W, 3) uint8`; `reduce` in {1, 2, 4, 8} decodes at 1/reduce scale."""
        flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                8: cv2.IMREAD_REDUCED_COLOR_8}[reduce]
        out = []
        for c, data in enumerate(self.jpeg_bytes(index)):
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flag)
            if img is None:
                raise OccDataError(f"corrupt image data for sample {index} ({self.token(index)}), camera {c}")
            out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        return out

    def depth_points(self, index: int) -> list[np.ndarray]:
        """Per camera `(M_c, 3) float32` (u, v, depth) in original-image pixels."""
        self._check_index(index)
        return [np.asarray(a, dtype=np.float32) for a in self._flat_slice("depth/uvd", "depth/offsets", index)]

    def _check_index(self, index: int) -> None:
        if not 0 <= index < self.n_samples:
            raise OccDataError(f"sample index {index} out of range (store has {self.n_samples} samples)")


def _open_group(path: str, consolidated: bool = True) -> tuple[zarr.Group, bool]:
    """The store's root group (read-only), and whether its array metadata came consolidated."""
    # s3fs sends a HEAD before each whole-object GET, to split objects over its block size (50 MB) into
    # concurrent ranges; a store's objects are smaller, so with one stream per object each read is one request.
    options = {"max_concurrency": 1} if path.startswith(("s3://", "s3a://")) else None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # zarr: consolidated metadata is not (yet) in the v3 spec
            if consolidated:
                try:
                    group = zarr.open_group(path, mode="r", use_consolidated=True, zarr_format=3,
                                            storage_options=options)
                    return group, True
                except ValueError:  # no consolidated metadata (a store from before it, or after an attrs edit)
                    pass
            return zarr.open_group(path, mode="r", use_consolidated=False, zarr_format=3,
                                   storage_options=options), False
    except Exception as exc:  # noqa: BLE001 - every failure to open reads the same to a user
        raise OccDataError(f"not a readable occdata store: {path} ({type(exc).__name__})") from None


def _schema_arrays(group: zarr.Group) -> list[str]:
    attrs = group.attrs
    specs = per_sample(has_flow(attrs), grid_shape(attrs), camera_count(attrs))
    return [*(s.name for s in specs), *FLAT_ARRAYS]


def _array_files_agree(group: zarr.Group) -> bool:
    """Whether every schema array's own `zarr.json` says what the consolidated copy says (fetched
    concurrently: one round trip's worth of requests, however many samples)."""
    meta = group.metadata.consolidated_metadata
    flat = meta.flattened_metadata if meta is not None else {}
    names = _schema_arrays(group)
    if any(not isinstance(flat.get(n), ArrayV3Metadata) for n in names):
        return False
    store, proto = group.store, default_buffer_prototype()

    async def fetch() -> list:
        return await asyncio.gather(*(store.get(f"{n}/zarr.json", proto) for n in names))

    try:
        raws = sync(fetch())
        return all(raw is not None and ArrayV3Metadata.from_dict(json.loads(raw.to_bytes())) == flat[n]
                   for n, raw in zip(names, raws, strict=True))
    except Exception:  # noqa: BLE001 - unreadable or invalid: the array-by-array open names it
        return False


def open_store(path: str | Path, check_metadata: bool = True, packed: bool = False) -> StoreReader:
    """Open a store for reading: a local path or an fsspec URL (`file:///x.zarr`, `s3://...`).
    `check_metadata=False` trusts the consolidated metadata (a loader worker, after its parent checked);
    `packed` reads small arrays from their packed copies (the loader; see `StoreReader`)."""
    path = store_location(path)
    if "://" not in path and not Path(path).exists():
        raise OccDataError(f"store not found: {path}")
    return StoreReader(path, check_metadata, packed)
