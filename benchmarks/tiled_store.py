"""A store of any sample count made from a small built one, for loader-start and store-open figures.

`make_tiled_store(src, out, n)`: sample i of the new store replays sample `i % B` of `src`, a built
store of exactly one block of B samples (e.g. `tests/replicated_tree.py` built with
`--block-samples B`). The small per-sample arrays are written at full size, block by block as the build
writes them (chunks of B rows), with unique sample tokens, scenes of 40 keyframes (the last 15% in
`val`), and the temporal indices and checksums of that layout. The payload is not copied: every
block's label shards and the flat arrays' chunks are hard links to the source's files, and the
offsets of sample i are those of sample `i % B`. The small arrays are packed as the build's final
commit packs them (occdata.store.pack). So a 34,000-sample store costs ~100 MB of small
arrays and no image bytes, and the loader reads it exactly as a built one (`occdata verify` passes).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import zarr

from occdata.store.create import consolidate, create_arrays
from occdata.store.integrity import crc_rows
from occdata.store.layout import FLAT_ARRAYS, checksummed_names, per_sample
from occdata.store.pack import write_pack
from occdata.store.sample import temporal_indices

__all__ = ["make_tiled_store"]

SCENE_SAMPLES = 40  # nuScenes' keyframes per scene
VAL_SHARE = 0.15


def _tokens(n: int, width: int) -> np.ndarray:
    """`(n, width) uint8`: a unique 32-hex token per sample."""
    out = np.zeros((n, width), dtype=np.uint8)
    for i in range(n):
        out[i, :32] = np.frombuffer(hashlib.md5(f"tiled/{i}".encode()).hexdigest().encode(), dtype=np.uint8)
    return out


def _small_rows(src: zarr.Group, n: int, block: int) -> tuple[dict[str, np.ndarray], int]:
    """Every small (non-sharded) per-sample array of the new store, `(n, ...)`, and the scene count."""
    src_of = np.arange(n) % block
    scene = (np.arange(n) // SCENE_SAMPLES).astype(np.int32)
    in_scene = (np.arange(n) % SCENE_SAMPLES).astype(np.int32)
    n_scenes = int(scene[-1]) + 1
    first_val = n_scenes - max(1, round(VAL_SHARE * n_scenes))
    prev_index, prev_valid = temporal_indices(scene, in_scene)
    rows: dict[str, np.ndarray] = {}
    for spec in per_sample():
        if spec.sharded or spec.name in ("status/checksum", "status/state"):
            continue
        rows[spec.name] = np.asarray(src[spec.name][:])[src_of]
    rows["sample/token"] = _tokens(n, src["sample/token"].shape[-1])
    rows["sample/scene_index"] = scene
    rows["sample/index_in_scene"] = in_scene
    rows["sample/split"] = (scene >= first_val).astype(np.uint8)  # splits ["train", "val"]
    rows["sample/timestamp"] = rows["sample/timestamp"] + 500_000 * np.arange(n)
    rows["temporal/prev_index"] = prev_index
    rows["temporal/prev_valid"] = prev_valid
    rows["status/state"] = np.ones(n, dtype=np.uint8)
    checks = np.asarray(src["status/checksum"][:])[src_of]  # flat and sharded arrays: the source's rows
    for col, name in enumerate(checksummed_names()):
        if name in rows:
            checks[:, col] = crc_rows(rows[name])
    rows["status/checksum"] = checks
    return rows, n_scenes


def _link_tree(src: Path, dst: Path) -> None:
    """Hard-link every file under `src` to the same place under `dst`."""
    for path in src.rglob("*"):
        if path.is_file():
            target = dst / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.link(path, target)


def make_tiled_store(src_path: Path, out: Path, n: int) -> Path:
    """Write `out`: `n` samples replaying `src_path` (one complete block of B samples). Returns `out`."""
    src = zarr.open_group(str(src_path), mode="r")
    block = int(src["status/state"].chunks[0])
    if src["status/state"].shape[0] != block or not (np.asarray(src["status/state"][:]) == 1).all():
        raise ValueError(f"{src_path}: the source must be one complete block (B samples, block size B)")
    shutil.rmtree(out, ignore_errors=True)
    rows, n_scenes = _small_rows(src, n, block)
    attrs = dict(src.attrs)
    scenes = [{**attrs["scenes"][0], "name": f"tiled-{s:04d}", "token": hashlib.md5(f"scene/{s}".encode()).hexdigest(),
               "first_index": s * SCENE_SAMPLES, "num_samples": min(SCENE_SAMPLES, n - s * SCENE_SAMPLES)}
              for s in range(n_scenes)]
    attrs.update(n_samples=n, splits=["train", "val"], scenes=scenes, complete=True, errors=[])
    n_blocks = -(-n // block)
    regions = np.zeros((n_blocks, len(FLAT_ARRAYS), 2), dtype=np.int64)
    regions[:, :, :] = np.asarray(src["plan/regions"][:])[0, :, 1][None, :, None]
    regions[0] = np.asarray(src["plan/regions"][:])[0]
    root = zarr.open_group(str(out), mode="w")
    create_arrays(root, n, block, attrs, int(src["sample/token"].shape[-1]), regions)
    for name, data in rows.items():
        root[name][:] = data
    for name in FLAT_ARRAYS:
        _link_tree(src_path / name / "c", out / name / "c")
    for spec in per_sample():
        chunks = src_path / spec.name / "c"
        if spec.sharded and chunks.is_dir():
            for b in range(n_blocks):
                _link_tree(chunks / "0", out / spec.name / "c" / str(b))
    write_pack(root)  # as the build's final commit does
    consolidate(str(out))
    return out


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("-n", type=int, required=True)
    args = ap.parse_args()
    make_tiled_store(args.src, args.out, args.n)
    print(json.dumps({"store": str(args.out), "n_samples": args.n}))
