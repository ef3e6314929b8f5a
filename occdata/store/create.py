"""Creating a store: its arrays and root attributes, published only once complete (a rename
locally; an attribute marks a store still being created on an object store); opening an existing
one for --resume (same identity, readable commit flags)."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec
from zarr.core.sync import sync

from occdata.constants import CLASS_COLORS, CLASS_NAMES, FREE_LABEL
from occdata.errors import OccDataError
from occdata.fileio import remove_stale_temps
from occdata.runtime.storage import is_remote, join, read_bytes, remove_tree, sibling
from occdata.store.identity import build_identity, identity_diff
from occdata.store.labelgrid import grid_attr
from occdata.store.layout import (
    FLAT_ARRAYS,
    REGIONS,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    TOKEN_ARRAYS,
    camera_count,
    checksummed_names,
    grid_shape,
    has_flow,
    per_sample,
    schema_version,
    token_width,
)
from occdata.store.pack import drop_pack
from occdata.store.reader import StoreReader, store_location

if TYPE_CHECKING:
    from occdata.nuscenes import NuScenesDataset
    from occdata.store.config import BuildConfig

__all__ = ["STAGING_SUFFIX", "consolidate", "create_arrays", "grow_flat", "open_or_create", "resume_state",
           "root_attrs", "store_exists"]


def _compressor(name: str) -> Any:
    return None if name == "images/jpeg" else ZstdCodec(level=1)


def create_arrays(root: zarr.Group, n: int, block: int, attrs: dict[str, Any], tok_width: int,
                  regions: np.ndarray | None = None) -> None:
    """Every array of the layout for `n` samples in blocks of `block`, pending, and the root attributes.
    `regions` `(n_blocks, len(FLAT_ARRAYS), 2) int64`: the plan (`occdata.store.plan.plan_regions`);
    the flat arrays are as long as its end from the start (None: empty plan, empty flat arrays)."""
    flow = has_flow(attrs)
    n_check = len(checksummed_names(flow))
    for s in per_sample(flow, grid_shape(attrs), camera_count(attrs)):
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
    n_blocks = -(-n // block)
    if regions is None:
        regions = np.zeros((n_blocks, len(FLAT_ARRAYS), 2), dtype=np.int64)
    if regions.shape != (n_blocks, len(FLAT_ARRAYS), 2):
        raise OccDataError(f"a plan for {regions.shape[0]} blocks, but {n} samples make {n_blocks} blocks")
    for f, (name, (row, dtype, chunk_rows)) in enumerate(FLAT_ARRAYS.items()):
        end = int(regions[:, f, 1].max()) if n_blocks else 0
        root.create_array(
            name, shape=(end, *row), dtype=dtype, chunks=(chunk_rows, *row), fill_value=0,
            compressors=_compressor(name),
        )
    root.create_array(REGIONS, shape=regions.shape, dtype="int64", chunks=regions.shape, fill_value=0,
                      compressors=ZstdCodec(level=1))
    root[REGIONS][...] = regions
    # Every commit flag exists from the start (pending): with many writers, blocks commit in any
    # order, and an absent state chunk stays a sign of damage (occdata.store.integrity).
    root["status/state"].with_config({"write_empty_chunks": True})[:] = np.zeros(n, dtype=np.uint8)
    root.attrs.put(attrs)


def _flow_attr(grid_shape: list[int]) -> dict[str, Any]:
    """`attrs["flow"]`: labels/flow in words, on the store's label grid `(X, Y, Z)`."""
    return {
        "array": "labels/flow", "shape": f"(N, {', '.join(map(str, grid_shape))}, 2)", "dtype": "float32",
        "components": ["vx", "vy"], "unit": "m/s", "frame": "the grid's axes (key ego), velocity over the ground",
        "source": "the 'flow' array of the OpenOcc v2 labels.npz files read with --gts",
        "classes": "labels/semantics holds our (Occ3D) ids, mapped from OpenOcc v2's by name; OpenOcc v2 has no "
                   "'others' (class 0 never occurs)",
    }


def root_attrs(config: BuildConfig, ds: NuScenesDataset, split_names: list[str], gts: Path | None,
               label_format: str = "occ3d") -> dict[str, Any]:
    """The root attributes of a new store (`gts`: the labels folder read; `label_format` its files'
    format: "openocc-v2" makes a version-3 store with `labels/flow`, and says so in `flow` and in the
    build identity; "occ3d" leaves every attribute as it was before flow existed). The rig: cameras in
    `camera_order`; a rig other than nuScenes' also in `rig` (nuScenes stores stay as they were)."""
    rig = ds.rig
    flow = label_format == "openocc-v2"
    first = 0
    scenes = []
    for sc in ds.scenes:
        scenes.append({
            "name": sc.name, "token": sc.token, "split": sc.split, "location": sc.location,
            "description": sc.description, "first_index": first, "num_samples": len(sc.sample_tokens),
        })
        first += len(sc.sample_tokens)
    opts = config.options
    grid = grid_attr(config.grid)
    return {
        "schema": SCHEMA_NAME,
        "schema_version": schema_version(flow),
        "n_samples": len(ds.samples),
        "camera_order": list(rig.cameras),
        "class_names": list(CLASS_NAMES),
        "class_colors": [list(c) for c in CLASS_COLORS],
        "free_label": FREE_LABEL,
        "grid": grid,
        "splits": split_names,
        "scenes": scenes,
        "images": {"encoding": "jpeg", "scale": opts.image_scale,
                   "reencoded": opts.image_scale != 1.0, "jpeg_quality": opts.jpeg_quality if
                   opts.image_scale != 1.0 else None},
        "depth": {"columns": ["u", "v", "depth"], "pixel_frame": "original image pixels",
                  "min_depth": opts.min_depth, "lidar_sweeps": opts.lidar_sweeps,
                  "source": f"keyframe {' + '.join(rig.lidars)}" + (
                      f" + up to {opts.lidar_sweeps} previous sweeps{' of each' * (len(rig.lidars) > 1)}, motion-"
                      "compensated to each camera's timestamp" if opts.lidar_sweeps else "")},
        "bev": {"encoding": "uint32 bit field, bit c = class c present in the column",
                "free_bit": FREE_LABEL},
        "checksum_arrays": list(checksummed_names(flow)),
        "checksum": f"crc32 of each array's per-sample C-order bytes (flat arrays: its {len(rig.cameras)} camera "
                    "slices)",
        "build_identity": build_identity(config, ds, gts, label_format),
        "build_config": {"workers": config.cluster.workers, "on_error": config.on_error},
        "errors": [],
        "complete": False,
    } | ({"flow": _flow_attr(grid["shape"])} if flow else {}) | ({} if rig.is_nuscenes else {"rig": rig.as_attr()})


STAGING_SUFFIX = ".staging"  # <store>.staging: where schema-1 builds staged blocks (removed, never written now)
_CREATING = "occdata_creating"  # root attribute of a store whose layout is still being written (object stores)


def resume_state(root: zarr.Group) -> np.ndarray:
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


def store_exists(out: str) -> bool:
    """A store is there once its layout is complete (locally: the folder, published by rename, unless
    empty; on an object store: a root `zarr.json` not marked as still being created)."""
    if not is_remote(out):
        return os.path.lexists(out) and not (os.path.isdir(out) and not os.listdir(out))
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
    if root.attrs.get("schema_version") not in (SCHEMA_VERSION, schema_version(True)):
        raise OccDataError(
            f"cannot resume {out}: it was built by an older occdata (store schema {root.attrs.get('schema_version')}, "
            f"this one writes {SCHEMA_VERSION}); it stays readable, but to finish it build again into a new --out"
        )
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
        remove_stale_temps(out, recursive=True)  # atomic-write leftovers of a killed run (we hold the lock)
    drop_pack(root)  # this run rewrites small arrays: readers use the chunks until its final commit repacks
    return root


def open_or_create(config: BuildConfig, ds: NuScenesDataset, split_names: list[str],
                   gts: Path | None, plan: Callable[[], np.ndarray],
                   label_format: str = "occ3d") -> tuple[zarr.Group, str]:
    """The store to write, and its location (a local path or a URL). `plan()` gives a new store's
    regions (`create_arrays`); a resumed store keeps its own."""
    out = store_location(config.out)
    attrs = root_attrs(config, ds, split_names, gts, label_format)
    if store_exists(out):
        return _open_existing(config, out, attrs), out
    remove_tree(sibling(out, STAGING_SUFFIX))  # left by an earlier store of that name: not ours
    tok_width = token_width(_all_tokens(ds))
    if is_remote(out):  # no rename on an object store: the root is marked until the layout is complete
        root = zarr.open_group(out, mode="w", attributes={_CREATING: True})
        create_arrays(root, len(ds.samples), config.block_samples, attrs, tok_width, plan())
        consolidate(out)
        return zarr.open_group(out, mode="r+", use_consolidated=False), out
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(out + ".creating")
    shutil.rmtree(tmp, ignore_errors=True)
    root = zarr.open_group(tmp, mode="w")
    create_arrays(root, len(ds.samples), config.block_samples, attrs, tok_width, plan())
    consolidate(str(tmp))
    tmp.rename(out)  # the store appears only once its layout is complete
    return zarr.open_group(out, mode="r+", use_consolidated=False), out


def _all_tokens(ds: NuScenesDataset) -> Iterator[str]:
    for s in ds.samples:
        yield s.token
        yield s.lidar.token
        yield from (c.token for c in s.cameras)


def grow_flat(root: zarr.Group, regions: np.ndarray) -> bool:
    """Each flat array at least as long as the plan's end (after `relocate`); True if one grew (the
    caller then rewrites the consolidated metadata that tasks read)."""
    grown = False
    for f, name in enumerate(FLAT_ARRAYS):
        arr = root[name]
        end = int(regions[:, f, 1].max()) if len(regions) else 0
        if arr.shape[0] < end:  # growing deletes nothing: skip zarr's walk over the old chunks
            sync(arr._async_array.resize((end, *arr.shape[1:]), delete_outside_chunks=False))
            grown = True
    return grown


def consolidate(out: str) -> None:
    """Rewrite the consolidated metadata (one read gives every array's metadata, on S3 too)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zarr: consolidated metadata is not (yet) in the v3 spec
        zarr.consolidate_metadata(out)
