"""Issue 12 items 10 (store side), 11 and 12: writers of a store under faults and misuse.

Each fault gives ONE `Error:` line (no traceback) and nothing half-written that a later run trips on.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from test_store_build import store_digest

from cli.fastocc_cli import main as fastocc_main
from cli.occdata_cli import main
from occdata.runtime.lock import store_lock
from occdata.store.build import BuildConfig, build_store
from occdata.store.layout import STATE_DONE, STATE_ERROR
from occdata.store.reader import open_store

REPO = Path(__file__).resolve().parents[1]


def _cli(*args: str, cli=main) -> tuple[int, str]:
    r = CliRunner().invoke(cli, list(args))
    return r.exit_code, r.output


def _one_error_line(text: str) -> str:
    assert "Traceback" not in text, text
    lines = [ln for ln in text.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1, text
    return lines[0]


@pytest.fixture
def store(synth_store: Path, tmp_path: Path) -> Path:
    out = tmp_path / "s.zarr"
    shutil.copytree(synth_store, out)
    return out


@pytest.fixture
def world(synth_root: Path, tmp_path: Path) -> Path:
    out = tmp_path / "world"
    shutil.copytree(synth_root, out)
    return out


def _build_args(root: Path, out: Path, *extra: str) -> list[str]:
    return ["build", "--root", str(root), "--gts", str(root / "gts"), "--out", str(out), "--no-progress", *extra]


# --- 11: one writer at a time ------------------------------------------------------------------------
def test_second_writer_is_told_who_holds_the_lock(synth_root: Path, store: Path, tmp_path: Path) -> None:
    out = tmp_path / "new.zarr"
    with store_lock(out, "build"):
        code, text = _cli(*_build_args(synth_root, out))
        line = _one_error_line(text)
        assert code == 1 and "being written by another process" in line
        assert f"pid {os.getpid()}" in line and "host" in line and "started 20" in line and "`occdata build`" in line
    assert not out.exists() and not list(tmp_path.glob("*.creating"))
    with store_lock(store, "visibility"):
        code, text = _cli("bev-gt", "--store", str(store), "--no-progress")
        assert code == 1 and "`occdata visibility`" in _one_error_line(text)
    code, text = _cli("bev-gt", "--store", str(store), "--no-progress")  # released: works
    assert code == 0, text


def test_two_concurrent_builds_to_one_out(synth_root: Path, tmp_path: Path) -> None:
    """Was: one failed with a `.partial` file error, or both failed and left `*.creating` behind."""
    out = tmp_path / "race.zarr"
    cmd = [sys.executable, "-m", "cli.occdata_cli", *_build_args(synth_root, out, "--block-samples", "2")]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    procs = [subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=300), p.stdout.read() + p.stderr.read()) for p in procs]
    assert sorted(code for code, _ in results) == [0, 1], results
    (loser,) = [text for code, text in results if code == 1]
    assert "Traceback" not in loser
    assert "being written by another process" in loser or "store exists" in loser, loser
    assert not list(tmp_path.glob("*.creating"))
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text


# --- 12: resume ----------------------------------------------------------------------------------------
def test_resume_names_the_options_that_differ(synth_root: Path, store: Path) -> None:
    code, text = _cli("build", "--root", str(synth_root), "--out", str(store), "--resume", "--image-scale", "0.5",
                      "--block-samples", "4", "--no-progress")
    line = _one_error_line(text)
    assert code == 1
    assert "--image-scale: store 1.0, now 0.5" in line and "--block-samples: store 32, now 4" in line
    # only what differs: --gts defaults to <root>/gts, the folder the store was built from
    assert "--root" not in line and "--split" not in line and "--gts" not in line


def test_resume_retries_samples_that_failed_under_skip(world: Path, synth_store: Path, tmp_path: Path) -> None:
    """Was: a sample that failed under --on-error skip stayed failed; only a full rebuild cleared it."""
    samples = json.loads((world / "v1.0-mini" / "sample_data.json").read_text())
    row = next(r for r in samples if r["filename"].endswith(".jpg") and r["is_key_frame"])
    jpg = world / row["filename"]
    good = jpg.read_bytes()
    jpg.write_bytes(good[: len(good) // 2])
    out = tmp_path / "r.zarr"
    code, text = _cli(*_build_args(world, out, "--on-error", "skip"))
    assert code == 0, text
    state = open_store(out).state
    (bad,) = np.flatnonzero(state == STATE_ERROR)
    code, text = _cli(*_build_args(world, out, "--on-error", "skip", "--resume"))  # still broken: still failed
    assert code == 0 and "1 error," in text and "(1 processed" in text
    jpg.write_bytes(good)  # fix the input
    code, text = _cli(*_build_args(world, out, "--resume"))
    assert code == 0 and "0 errors" in text and "(1 processed" in text, text
    reader = open_store(out)
    assert (reader.state == STATE_DONE).all() and reader.attrs["errors"] == [] and reader.attrs["complete"]
    # The retried sample's block stays where the plan put it: the store is the uninterrupted build's, byte
    # for byte (offsets included), not a block moved to the end with its old bytes left behind.
    assert store_digest(out) == store_digest(synth_store)
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text


def test_a_block_whose_lidar_file_grew_moves_to_the_end(world: Path, synth_store: Path, tmp_path: Path) -> None:
    """The one case where a block moves: its payload outgrows its region. A keyframe LiDAR file cut to
    one point and a byte (its sample fails; the plan counts 1 point) is replaced by a denser one (its
    points 8 times), so block 1 (one sample a block) no longer fits; --resume gives it a region after
    the last one (recorded in plan/regions), the other blocks stay, and `verify` passes."""
    rows = json.loads((world / "v1.0-mini" / "sample_data.json").read_text())
    row = next(r for r in rows if r["filename"].endswith(".pcd.bin") and r["is_key_frame"])
    lidar = world / row["filename"]
    good = lidar.read_bytes()
    lidar.write_bytes(good[:21])
    out = tmp_path / "g.zarr"
    code, text = _cli(*_build_args(world, out, "--on-error", "skip", "--block-samples", "1"))
    assert code == 0 and "1 error," in text, text
    (bad,) = np.flatnonzero(open_store(out).state == STATE_ERROR)
    before = zarr.open_group(str(out), mode="r")["plan/regions"][:]
    lidar.write_bytes(good * 8)
    code, text = _cli(*_build_args(world, out, "--block-samples", "1", "--resume"))
    assert code == 0 and "0 errors" in text, text
    after = zarr.open_group(str(out), mode="r")["plan/regions"][:]
    b = int(bad)
    assert after[b, 1, 0] == before[:, 1, 1].max() and after[b, 0].tolist() == before[b, 0].tolist()
    assert (np.delete(after, b, axis=0) == np.delete(before, b, axis=0)).all()
    reader = open_store(out)
    assert int(reader.small("depth/offsets")[b, 0, 0]) == after[b, 1, 0]
    for got, ref in zip(reader.depth_points(b), open_store(synth_store).depth_points(b), strict=True):
        np.testing.assert_array_equal(got, np.tile(ref, (8, 1)))  # the same points, 8 times
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text


# --- 10: a full disk -----------------------------------------------------------------------------------
def _enospc(path: object) -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def test_build_on_a_full_disk_then_resume(synth_root: Path, tmp_path: Path, monkeypatch) -> None:
    import zarr.storage._local as local

    ref = tmp_path / "ref.zarr"
    build_store(BuildConfig(root=synth_root, out=ref, gts=synth_root / "gts", block_samples=2, progress=False))
    real_put, calls = local._put, [0]

    def full_disk(path, value, exclusive=False):  # the disk fills up after some chunk writes
        if "/c/" in str(path):
            calls[0] += 1
            if calls[0] > 40:
                raise _enospc(path)
        return real_put(path, value, exclusive=exclusive)

    monkeypatch.setattr(local, "_put", full_disk)
    out = tmp_path / "full.zarr"
    code, text = _cli(*_build_args(synth_root, out, "--block-samples", "2"))
    line = _one_error_line(text)
    assert code == 1 and "No space left on device" in line and "--resume" in line
    monkeypatch.setattr(local, "_put", real_put)
    assert 0 < int((open_store(out).state != 0).sum()) < 6
    code, text = _cli(*_build_args(synth_root, out, "--block-samples", "2", "--resume"))
    assert code == 0, text
    assert store_digest(out) == store_digest(ref)


def test_dump_on_a_full_disk_leaves_nothing(store: Path, tmp_path: Path, monkeypatch) -> None:
    def full_disk(file, **arrays):  # the archive half-written into the temporary file
        file.write(b"PK\x03\x04partial")
        raise _enospc(file.name)

    monkeypatch.setattr(np, "savez_compressed", full_disk)
    out = tmp_path / "d.npz"
    code, text = _cli("dump", "--store", str(store), "-i", "0", "--out", str(out))
    assert code == 1 and "No space left on device" in _one_error_line(text)
    assert list(tmp_path.iterdir()) == [store]  # no d.npz, no temporary file


@pytest.mark.parametrize("cmd", ["show-batch", "check-projection"])
def test_image_writers_on_a_full_disk_leave_nothing(store: Path, tmp_path: Path, monkeypatch, cmd: str) -> None:
    def full_disk(fd: int) -> None:  # the bytes are written; the disk fills when they are flushed
        raise _enospc(f"fd {fd}")

    monkeypatch.setattr(os, "fsync", full_disk)
    out = tmp_path / "pic" / "b.png"
    cli = fastocc_main if cmd == "show-batch" else main
    code, text = _cli(cmd, "--store", str(store), "-i", "0", "--out", str(out), cli=cli)
    assert code == 1 and "No space left on device" in _one_error_line(text)
    assert not list(out.parent.iterdir())


@pytest.mark.parametrize("cmd", ["show-batch", "check-projection"])
def test_unknown_image_extension(store: Path, tmp_path: Path, cmd: str) -> None:
    cli = fastocc_main if cmd == "show-batch" else main
    code, text = _cli(cmd, "--store", str(store), "--out", str(tmp_path / "x.jpgg"), cli=cli)
    assert code == 1 and "unknown image type '.jpgg'" in _one_error_line(text)


# --- 10: damaged metadata and status chunks -------------------------------------------------------
READERS = [
    ("info",), ("verify", "--no-progress"), ("dump", "-i", "0", "--out", "{tmp}/d.npz"),
    ("check-projection", "-i", "0", "--out", "{tmp}/p.png"), ("bev-gt", "--no-progress"),
    ("show-batch", "-i", "0", "--out", "{tmp}/b.png"),
]


def _run_reader(args: tuple[str, ...], store: Path, tmp: Path) -> tuple[int, str]:
    cli = fastocc_main if args[0] == "show-batch" else main
    return _cli(args[0], "--store", str(store), *[a.format(tmp=tmp) for a in args[1:]], cli=cli)


def _damage(store: Path, kind: str) -> str:
    """Damage the store; returns a phrase the error line must contain."""
    if kind == "zero_length_state":
        (chunk,) = [p for p in (store / "status/state/c").rglob("*") if p.is_file()]
        chunk.write_bytes(b"")
        return "status/state"
    if kind == "array_json_invalid":
        (store / "labels/semantics/zarr.json").write_text("{ not json")
        return "labels/semantics"
    if kind == "array_shape":
        meta = json.loads((store / "labels/semantics/zarr.json").read_text())
        meta["shape"] = [6, 200, 200, 8]
        meta["chunk_grid"]["configuration"]["chunk_shape"] = [6, 200, 200, 8]
        meta["codecs"][0]["configuration"]["chunk_shape"] = [1, 200, 200, 8]
        (store / "labels/semantics/zarr.json").write_text(json.dumps(meta))
        return "labels/semantics has shape (6, 200, 200, 8)"
    if kind in ("n_samples", "n_samples_type"):
        meta = json.loads((store / "zarr.json").read_text())
        meta["attributes"]["n_samples"] = 7 if kind == "n_samples" else "six"
        (store / "zarr.json").write_text(json.dumps(meta))
        return "(7," if kind == "n_samples" else "n_samples is 'six'"
    if kind == "root_json_invalid":
        (store / "zarr.json").write_text("{")
        return "not a readable"
    raise AssertionError(kind)


DAMAGE = ["zero_length_state", "array_json_invalid", "array_shape", "n_samples", "n_samples_type",
          "root_json_invalid"]


@pytest.mark.parametrize("kind", DAMAGE)
def test_damaged_store_gives_one_line_everywhere(store: Path, tmp_path: Path, kind: str, synth_root: Path) -> None:
    needle = _damage(store, kind)
    for args in READERS:
        code, text = _run_reader(args, store, tmp_path)
        assert code == 1, (args, text)
        assert needle in _one_error_line(text), (args, text)
    code, text = _cli(*_build_args(synth_root, store, "--resume"))
    assert code == 1 and needle in _one_error_line(text), text
    assert not list(tmp_path.glob("*.npz")) and not list(tmp_path.glob("*.png"))


def test_zero_length_state_chunk_resume_says_how_to_recover(store: Path, synth_root: Path,
                                                            synth_store: Path) -> None:
    _damage(store, "zero_length_state")
    code, text = _cli(*_build_args(synth_root, store, "--resume"))
    line = _one_error_line(text)
    assert "delete status/state/c/0 inside the store and rerun --resume" in line
    (store / "status/state/c/0").unlink()
    code, text = _cli(*_build_args(synth_root, store, "--resume"))
    assert code == 0 and "(6 processed" in text, text
    assert store_digest(store) == store_digest(synth_store)
    assert zarr.open_group(str(store), mode="r").attrs["complete"]


def test_a_schema_1_store_reads_but_does_not_resume(synth_root: Path, store: Path) -> None:
    """Issue 33 bumped the schema to 2 (planned regions): a version-1 store stays readable, and
    `--resume` of it is one line saying to build again into a new --out."""
    zarr.open_group(str(store), mode="r+").attrs["schema_version"] = 1
    assert open_store(store).jpeg_bytes(0)
    code, text = _cli(*_build_args(synth_root, store, "--resume"))
    line = _one_error_line(text)
    assert code == 1 and "store schema 1" in line and "new --out" in line


# --- no metadata write while tasks run (issue 40, item 4) ---------------------------------------------
def _arrays_on_disk(out: Path) -> set[str]:
    return {str(p.parent.relative_to(out)) for p in out.rglob("zarr.json")
            if json.loads(p.read_text())["node_type"] == "array"}


def _consolidated_arrays(out: Path) -> set[str]:
    meta = json.loads((out / "zarr.json").read_text()).get("consolidated_metadata") or {"metadata": {}}
    return {k for k, v in meta["metadata"].items() if v["node_type"] == "array"}


def _spy_on_the_run(monkeypatch: pytest.MonkeyPatch, out: Path) -> tuple[list[str], list[bool]]:
    """Metadata keys written while `run_tasks` runs (by the tasks, here in this process, or by the client
    between them), and after each task whether the consolidated metadata still lists every array."""
    from zarr.storage import LocalStore

    import occdata.store.build as build_mod

    running, written, intact = [False], [], []
    real_set, real_run = LocalStore.set, build_mod.run_tasks

    async def spy_set(self, key, value):
        if running[0] and key.endswith("zarr.json"):
            written.append(key)
        return await real_set(self, key, value)

    def spy_run(client, tasks, **kw):
        def on_result(task, result):
            follow_ups = kw["on_result"](task, result)
            intact.append(_consolidated_arrays(out) == _arrays_on_disk(out))
            return follow_ups

        running[0] = True
        try:
            return real_run(client, tasks, **{**kw, "on_result": on_result})
        finally:
            running[0] = False

    monkeypatch.setattr(LocalStore, "set", spy_set)
    monkeypatch.setattr(build_mod, "run_tasks", spy_run)
    return written, intact


def _break_first_keyframe_jpeg(world: Path) -> str:
    rows = json.loads((world / "v1.0-mini" / "sample_data.json").read_text())
    row = next(r for r in rows if r["filename"].endswith(".jpg") and r["is_key_frame"])
    jpg = world / row["filename"]
    jpg.write_bytes(jpg.read_bytes()[:1000])
    return row["sample_token"]


def test_skipped_errors_are_written_once_after_the_tasks(world: Path, monkeypatch: pytest.MonkeyPatch,
                                                         tmp_path: Path) -> None:
    """Was: each block's skipped errors rewrote the root attributes while later tasks ran, which drops
    the consolidated metadata every task opens (and a task could read a half-written zarr.json). Now no
    zarr.json is written while tasks run, the consolidated metadata lists every array after each task
    and at the end, and the error is recorded."""
    token = _break_first_keyframe_jpeg(world)
    out = tmp_path / "e.zarr"
    written, intact = _spy_on_the_run(monkeypatch, out)
    report = build_store(BuildConfig(root=world, out=out, gts=world / "gts", block_samples=1, on_error="skip",
                                     progress=False))
    assert report.n_errors == 1 and report.n_done == 5
    assert written == [], written
    assert len(intact) == 6 and all(intact), intact
    assert _consolidated_arrays(out) == _arrays_on_disk(out) and len(_arrays_on_disk(out)) > 10
    (err,) = zarr.open_consolidated(str(out), mode="r").attrs["errors"]
    assert err["token"] == token and "JPEG" in err["reason"], err
    assert open_store(out).state[err["index"]] == STATE_ERROR


def test_skipped_errors_are_kept_when_the_run_stops(world: Path, monkeypatch: pytest.MonkeyPatch,
                                                    tmp_path: Path) -> None:
    """A run that stops after a skipped error (here a bug in a later block's task) still records it,
    once, with the consolidated metadata rewritten; --resume then redoes that block."""
    import occdata.store.blocks as blocks

    token = _break_first_keyframe_jpeg(world)
    out = tmp_path / "k.zarr"
    real_convert = blocks.convert_block

    def bug_in_block_5(job):
        if job.block == 5:
            raise RuntimeError("planted bug in block 5")
        return real_convert(job)

    monkeypatch.setattr(blocks, "convert_block", bug_in_block_5)
    with pytest.raises(RuntimeError, match="planted bug"):
        build_store(BuildConfig(root=world, out=out, gts=world / "gts", block_samples=1, on_error="skip",
                                progress=False))
    group = zarr.open_consolidated(str(out), mode="r")
    (err,) = group.attrs["errors"]
    assert err["token"] == token and group.attrs["complete"] is False
    assert _consolidated_arrays(out) == _arrays_on_disk(out)
    monkeypatch.undo()
    report = build_store(BuildConfig(root=world, out=out, gts=world / "gts", block_samples=1, on_error="skip",
                                     progress=False, resume=True))
    assert report.n_errors == 1 and report.n_done == 5
    assert [e["token"] for e in zarr.open_group(str(out), mode="r").attrs["errors"]] == [token]
