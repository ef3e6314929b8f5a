"""`occdata build` and friends on the real keyframe and on replayed multi-scene trees."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from gates import gated_tree
from proc_tools import wait_for
from reference.store_bev import bev_bits_reference
from replicated_tree import make_replicated_tree
from test_nuscenes_reader import DEVKIT_COUNTS

from cli.occdata_cli import main
from occdata.runtime.cluster import ClusterConfig
from occdata.store.bev import unpack_bev
from occdata.store.build import BuildConfig, build_store
from occdata.store.integrity import StoreIntegrity
from occdata.store.layout import FLAT_ARRAYS, STATE_DONE
from occdata.store.reader import open_store

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


def _stored_chunks(g: zarr.Group, name: str) -> list[np.ndarray]:
    """The stored chunks of a flat array, in row order (its address space is sparse: read no gap)."""
    arr = g[name]
    rows = int(arr.chunks[0])
    keys = StoreIntegrity(g).stored_keys(name)
    index = sorted(int(k.rsplit("/c/", 1)[1].split("/")[0]) for k in keys)
    return [np.asarray(arr[k * rows : (k + 1) * rows]) for k in index] + [np.array(index)]


def store_digest(path: Path) -> dict[str, str]:
    """sha256 of every array's logical content (flat arrays: their stored chunks and where they lie),
    plus the attrs that must match."""
    g = zarr.open_group(str(path), mode="r")
    out = {}
    for name, arr in sorted(g.members(max_depth=None)):
        if isinstance(arr, zarr.Array):
            parts = _stored_chunks(g, name) if name in FLAT_ARRAYS else [arr[:]]
            h = hashlib.sha256(str((arr.shape, arr.dtype)).encode())
            for data in parts:
                h.update(np.ascontiguousarray(data).tobytes())
            out[name] = h.hexdigest()
    attrs = dict(g.attrs)
    attrs.pop("build_config", None)
    if isinstance(attrs.get("build_identity"), dict):  # where the input lies is not content (gated copies)
        attrs["build_identity"] = {k: v for k, v in attrs["build_identity"].items() if k not in ("source_root", "gts")}
    out["attrs"] = hashlib.sha256(json.dumps(attrs, sort_keys=True).encode()).hexdigest()
    return out


@pytest.fixture(scope="module")
def tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory) -> Path:
    return make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path_factory.mktemp("rep") / "ns", 2, 6)


@pytest.fixture(scope="module")
def tree_store(tree, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("store") / "rep.zarr"
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=4, progress=False))
    return out


def test_real_keyframe_store_reproduces_devkit_counts(real_nuscenes_root, tmp_path) -> None:
    out = tmp_path / "real.zarr"
    code, text = _cli("build", "--root", str(real_nuscenes_root), "--out", str(out), "--no-progress")
    assert code == 0, text
    reader = open_store(out)
    assert reader.n_samples == 1 and reader.state.tolist() == [STATE_DONE]
    assert reader.token(0) == "ca9a282c9e77460f8360f564131a8af5"
    assert not reader.group["labels/present"][0]
    order = reader.attrs["camera_order"]
    for c, pts in enumerate(reader.depth_points(0)):
        u, v, d = pts.T
        devkit = (d > 1.0) & (u > 1) & (u < 1599) & (v > 1) & (v < 899)
        assert devkit.sum() == DEVKIT_COUNTS[order[c]]
        assert (d > 0).all() and (u >= 0).all() and (u < 1600).all() and (v < 900).all()
    # The original JPEG bytes are stored untouched.
    cam0 = sorted((real_nuscenes_root / "samples" / order[0]).iterdir())[0]
    assert reader.jpeg_bytes(0)[0] == cam0.read_bytes()
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text


def test_replayed_store_contents(tree_store, real_occ3d_label) -> None:
    reader = open_store(tree_store)
    assert reader.n_samples == 12 and (reader.state == STATE_DONE).all()
    assert reader.attrs["splits"] == ["train", "val"]
    assert reader.group["sample/split"][:].tolist() == [0] * 6 + [1] * 6
    with np.load(real_occ3d_label) as npz:
        sem = npz["semantics"]
        mask_camera = npz["mask_camera"]
    a = reader.sample_arrays(7)
    np.testing.assert_array_equal(a["labels/semantics"], sem)
    np.testing.assert_array_equal(a["labels/mask_camera"], mask_camera)
    np.testing.assert_array_equal(a["labels/bev"], bev_bits_reference(sem))
    # Temporal indices: sample 7 is the 2nd of scene 1 (store index 6..11).
    assert a["temporal/prev_index"].tolist() == [6] * 16
    assert a["temporal/prev_valid"].tolist() == [True] + [False] * 15
    b = reader.sample_arrays(11)
    assert b["temporal/prev_index"][:5].tolist() == [10, 9, 8, 7, 6]
    assert b["temporal/prev_valid"].sum() == 5
    # Pose shift of 4 m per sample: T_cur_from_prev moves the previous key ego 4 m "back".
    T_cur = b["pose/T_global_from_keyego"]
    T_prev = reader.sample_arrays(10)["pose/T_global_from_keyego"]
    delta = (np.linalg.inv(T_cur) @ T_prev)[:3, 3]
    assert abs(np.linalg.norm(delta) - 4.0) < 1e-6


def test_dump_and_check_projection(tree_store, tmp_path) -> None:
    code, text = _cli("dump", "--store", str(tree_store), "-i", "3", "--out", str(tmp_path / "s.npz"))
    assert code == 0, text
    with np.load(tmp_path / "s.npz", allow_pickle=False) as d:
        assert d["images"].shape == (6, 900, 1600, 3)
        assert d["bev"].shape == (18, 200, 200)
        np.testing.assert_array_equal(d["bev"], unpack_bev(bev_bits_reference(d["semantics"])))
        assert d["K"].shape == (6, 3, 3) and d["T_keyego_from_cam"].shape == (6, 4, 4)
        assert all(d[f"depth_uvd_{c}"].shape[1] == 3 for c in range(6))
    code, text = _cli("check-projection", "--store", str(tree_store), "-i", "0", "--out", str(tmp_path / "p.png"))
    assert code == 0, text
    assert (tmp_path / "p.png").stat().st_size > 10_000
    code, text = _cli("dump", "--store", str(tree_store), "-i", "99", "--out", str(tmp_path / "x.npz"))
    assert code != 0 and "out of range" in text


def test_info_json(tree_store) -> None:
    code, text = _cli("info", "--store", str(tree_store), "--json")
    assert code == 0
    info = json.loads(text)
    assert info["samples"] == 12 and info["labelled"] == 12 and info["scenes"] == 2
    assert info["arrays"]["labels/semantics"]["shards"] == [4, 200, 200, 16]
    assert info["attrs"]["class_names"][17] == "free"


def test_bev_gt_command_rewrites_and_keeps_checksums(tree_store, tmp_path) -> None:
    import shutil

    copy = tmp_path / "copy.zarr"
    shutil.copytree(tree_store, copy)
    g = zarr.open_group(str(copy), mode="r+")
    g["labels/bev"][2] = 0  # damage, then regenerate
    code, _ = _cli("verify", "--store", str(copy), "--no-progress")
    assert code != 0
    code, text = _cli("bev-gt", "--store", str(copy), "--no-progress")
    assert code == 0 and "12 labelled" in text
    code, text = _cli("verify", "--store", str(copy), "--no-progress")
    assert code == 0, text
    assert store_digest(copy) == store_digest(tree_store)


def test_existing_store_needs_resume_and_same_inputs(tree, tree_store) -> None:
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(tree_store),
                      "--block-samples", "4", "--no-progress")
    assert code != 0 and "store exists" in text and "--resume" in text
    code, text = _cli("build", "--root", str(tree), "--out", str(tree_store), "--resume", "--no-progress")
    assert code != 0 and "other inputs or options" in text
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(tree_store),
                      "--block-samples", "4", "--resume", "--no-progress")
    assert code == 0 and "0 processed" in text


def test_resume_removes_a_killed_writers_temporaries(tree, tree_store, tmp_path) -> None:
    """Was: SIGTERM while zarr's LocalStore wrote a chunk left `<chunk>.<uuid hex>.partial` for good, and
    the chunk listing took it for a chunk. Both kinds of leftovers are ignored, and removed on --resume."""
    copy = tmp_path / "t.zarr"
    shutil.copytree(tree_store, copy)
    chunk_dir = next(p.parent for p in sorted((copy / "images/jpeg").rglob("*")) if p.is_file() and "/c/" in str(p))
    hex32 = "a05beeca6d4f4a738453cbd0f03dd535"
    planted = [chunk_dir / f"1.{hex32}.partial", copy / f"zarr.{hex32}.partial", chunk_dir / ".0.k2j3h4.tmp"]
    for p in planted:
        p.write_bytes(b"half a chunk")
    keep = chunk_dir.parent / "notes.partial"  # not a temporary's name: left alone
    keep.write_bytes(b"x")
    assert store_digest(copy) == store_digest(tree_store)
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(copy),
                      "--block-samples", "4", "--resume", "--no-progress")
    assert code == 0, text
    assert not any(p.exists() for p in planted) and keep.exists()


@pytest.mark.parametrize("workers", [1, 2])
def test_parallel_build_is_identical(tree, tree_store, tmp_path, workers: int) -> None:
    out = tmp_path / "w.zarr"
    build_store(BuildConfig(root=tree, out=out, gts=tree / "gts", block_samples=4,
                            cluster=ClusterConfig(workers=workers), progress=False))
    assert store_digest(out) == store_digest(tree_store)


def _committed(path: Path) -> int:
    try:
        return int((zarr.open_group(str(path), mode="r")["status/state"][:] != 0).sum())
    except Exception:  # noqa: BLE001 - store not created yet or mid-write
        return 0


@pytest.mark.parametrize("kill_after", [0, 3, 7])
def test_kill9_and_resume_is_identical(tree, tree_store, tmp_path, kill_after: int) -> None:
    """kill -9 once the store exists / `kill_after` samples are committed; the last sample is a FIFO gate,
    so the build cannot have finished first."""
    root, gate = gated_tree(tree, tmp_path / "g", 1, 5)  # store index 11, the last block
    out = tmp_path / "k.zarr"
    cmd = [sys.executable, "-m", "cli.occdata_cli", "build", "--root", str(root), "--gts", str(root / "gts"),
           "--out", str(out), "--block-samples", "4", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    reached = wait_for(lambda: proc.poll() is not None or (
        out.exists() if kill_after == 0 else _committed(out) >= kill_after), 300, 0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert reached and proc.returncode == -signal.SIGKILL, f"the build ended or stalled first ({proc.returncode})"
    assert _committed(out) < 12
    done = threading.Event()
    gate.serve(done.is_set)
    try:
        code, text = _cli("build", "--root", str(root), "--gts", str(root / "gts"), "--out", str(out),
                          "--block-samples", "4", "--resume", "--no-progress")
    finally:
        done.set()
    assert code == 0, text
    assert store_digest(out) == store_digest(tree_store)
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text
