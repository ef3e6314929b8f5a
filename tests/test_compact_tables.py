"""Issue 48: the tables' rows kept as columns and the keyframe records packed, made again when asked.

Truths: the JSON files themselves (each kept row equals the file's row), the reader's own record made
from the tables (a pack round trip, field by field), and the old whole-list definition of the sweep
check's counts."""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import os
import pickle
import subprocess
import sys
import tracemalloc
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from occdata.errors import OccDataError
from occdata.nuscenes import load_nuscenes
from occdata.nuscenes import reader as R
from occdata.nuscenes.columns import ColumnTable
from occdata.nuscenes.records import LazySamples
from occdata.nuscenes.tables import TokenSet, load_table
from occdata.store.inputs import Histories, check_sweep_files

REPO = Path(__file__).resolve().parents[1]


def _same(a: Any, b: Any) -> bool:
    """Equal, NaN equal to NaN (Lyft writes `NaN` for a LiDAR row's width)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b and (type(a) is type(b) or {type(a), type(b)} == {int, float})


@pytest.fixture(params=["memory", "paged"])
def paging(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Tables as read (their columns paged out past a MiB: the real ones are smaller), or with every
    column paged to its temporary file after 64 bytes and every token set spilled after 7 tokens."""
    from occdata.nuscenes import columns, tables

    if request.param == "paged":
        monkeypatch.setattr(columns._Paged, "_FLUSH", 64)
        monkeypatch.setattr(tables, "_SET_IN_MEMORY", 7)
    return str(request.param)


@pytest.mark.parametrize("table", ["sample_data", "ego_pose", "sample"])
def test_column_rows_equal_the_files_rows(table: str, real_seq_root: Path, real_lyft_root: Path, paging: str) -> None:
    for path in (real_seq_root / "v1.0-mini" / f"{table}.json", real_lyft_root / "train_data" / f"{table}.json"):
        rows = json.loads(path.read_text())
        kept = load_table(path, columns=True)
        assert isinstance(kept, ColumnTable) and len(kept) == len(rows)
        assert list(kept) == [r["token"] for r in rows]  # file order
        for r in rows:
            assert _same(kept[r["token"]], r), (path, r["token"])
        # numbers keep their type: nuScenes' integer timestamps, Lyft's float ones
        assert type(kept[rows[0]["token"]]["timestamp"]) is type(rows[0]["timestamp"])
        assert kept.nbytes() < 0.6 * len(path.read_bytes())  # the text of the file, not its Python objects
        if paging == "paged":  # in memory: the index, slots and hashes (32 bytes a row), the tails
            assert kept.nbytes() < 32 * len(rows) + 64 * 24, kept.nbytes()
            kept.release()  # the pages mapped out are read again from the page cache
            assert all(_same(kept[r["token"]], r) for r in rows[::7])


def test_rows_that_do_not_fit_the_columns_are_kept_whole(tmp_path: Path) -> None:
    base = {"token": "a", "timestamp": 1, "rotation": [1.0, 0.0, 0.0, 0.0], "name": "x", "key": True}
    odd = [
        {**base, "token": "b", "extra": 1},  # another key
        {**base, "token": "c", "timestamp": "soon"},  # a value of another kind
        {**base, "token": "d", "timestamp": 2**60},  # beyond float64's exact integers
        {**base, "token": "e", "rotation": [1.0, 0.0]},  # a list of another length
        {**base, "token": "f", "name": "\ud800"},  # a lone surrogate
        {**base, "token": "g", "key": 1},  # a number where a boolean was
        {k: v for k, v in base.items() if k != "name"} | {"token": "h"},  # a key missing
    ]
    fine = {**base, "token": "i", "timestamp": 2.5, "rotation": [0, 1, 0, 0]}
    rows = [base, *odd, fine]
    path = tmp_path / "t.json"
    path.write_text(json.dumps(rows))
    kept = load_table(path, columns=True)
    assert list(kept) == [r["token"] for r in rows]
    for r in rows:
        assert _same(kept[r["token"]], r) and kept.position(r["token"]) == rows.index(r)
    assert kept["i"]["rotation"] == [0.0, 1.0, 0.0, 0.0]  # list members read back as floats
    assert kept["d"]["timestamp"] == 2**60 and kept["c"]["timestamp"] == "soon"
    assert "z" not in kept and kept.position(3) == -1 and kept.get("z") is None
    with pytest.raises(KeyError):
        kept["z"]


def test_column_tables_refuse_and_report_duplicates_as_the_dict_tables_do(tmp_path: Path) -> None:
    row = {"token": "a", "timestamp": 1}
    path = tmp_path / "t.json"
    path.write_text(json.dumps([row, {"token": "b", "timestamp": 2}, row]))
    notes: list[str] = []
    kept = load_table(path, warn=notes.append, columns=True)
    assert list(kept) == ["a", "b"] and len(notes) == 1 and "identical duplicate" in notes[0]
    path.write_text(json.dumps([row, {"token": "a", "timestamp": 3}]))
    with pytest.raises(OccDataError, match="duplicate token .*'a'.*'timestamp'"):
        load_table(path, columns=True)


def test_hash_lookups_answer_many_tokens_at_once(real_seq_root: Path) -> None:
    path = real_seq_root / "v1.0-mini" / "sample_data.json"
    every = TokenSet()
    kept = load_table(path, keep=lambda r: r["is_key_frame"], columns=True, tokens=every)
    rows = json.loads(path.read_text())
    tokens = [r["token"] for r in rows]
    pos = kept.positions_of_hashes(np.array([hash(t) for t in tokens], dtype=np.int64))
    for t, p in zip(tokens, pos, strict=True):
        assert p == kept.position(t)
        assert (p >= 0) == any(r["token"] == t and r["is_key_frame"] for r in rows)
    found = every.has_hashes(np.array([hash(t) for t in tokens] + [hash("nope")]))
    assert found.tolist() == [True] * len(tokens) + [False]


@pytest.mark.parametrize("in_memory", [1, 50, 1 << 20])
def test_a_token_set_answers_the_same_spilled_or_held(in_memory: int) -> None:
    rng = np.random.default_rng(3)
    tokens = [f"{rng.integers(1 << 62):x}" for _ in range(700)]
    tokens += [tokens[i] for i in (5, 5, 17, 699)]  # repeats: 5 three times
    every = TokenSet(in_memory)
    for t in tokens:
        every.add(t)
    counts = Counter(hash(t) for t in tokens)
    assert every.repeated() == {h for h, c in counts.items() if c > 1} and len(every.repeated()) == 3
    queries = tokens[::3] + [f"absent-{i}" for i in range(300)]
    truth = [q in set(tokens) for q in queries]
    assert every.has_hashes(np.array([hash(q) for q in queries], dtype=np.int64)).tolist() == truth
    assert [q in every for q in queries[:40] + queries[-40:]] == truth[:40] + truth[-40:]
    assert every.hits(queries) == [q for q, t in zip(queries, truth, strict=True) if t]
    every.add("late")  # added after the queries: seen by the next ones
    assert "late" in every and every.has_hashes(np.zeros(0, np.int64)).tolist() == []


def test_a_bucket_spill_gives_each_bucket_its_rows_in_order() -> None:
    from occdata.nuscenes.spill import BUCKETS, BucketSpill, bucket_of

    dtype = np.dtype([("k", "<i8"), ("h", "<i8")])
    rng = np.random.default_rng(5)
    rows = np.zeros(5000, dtype)
    rows["k"] = np.arange(5000)
    rows["h"] = rng.integers(-(1 << 63), (1 << 63) - 1, 5000, dtype=np.int64)
    spilled = BucketSpill(dtype, "h", in_memory=300)
    for c0 in range(0, 5000, 700):
        spilled.add(rows[c0:c0 + 700])
    got = [spilled.bucket(b) for b in range(BUCKETS)]
    for b, part in enumerate(got):
        np.testing.assert_array_equal(part, rows[bucket_of(rows["h"]) == b])  # its rows, in the order added
    assert sum(map(len, got)) == 5000 and sum(len(p) > 0 for p in got) == BUCKETS
    assert bucket_of(np.array([-1, 0, (1 << 63) - 1], np.int64)).tolist() == [63, 0, 31]


def test_a_large_token_set_holds_its_hashes_on_disk() -> None:
    """A million tokens: 8 MB of hashes held in memory before (24 MB while `repeated` sorted them); now
    2**14 at most (128 KiB) and the spill's 1 MiB write buffer, the rest in 64 buckets on disk, and a
    query reads one bucket at a time."""
    every = TokenSet(1 << 14)
    tracemalloc.start()
    for i in range(1_000_000):
        every.add(f"tok-{i}")
    held = tracemalloc.get_traced_memory()[0]
    found = every.has_hashes(np.array([hash("tok-7"), hash("tok-999999"), hash("tok-1000000")], dtype=np.int64))
    repeated = every.repeated()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert found.tolist() == [True, True, False] and repeated == set()
    assert held < 2_000_000, held
    assert peak < 3_000_000, peak  # one bucket (~15,600 hashes) and its sort, not the whole set


def _assert_same_record(a: Any, b: Any, where: str = "") -> None:
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            _assert_same_record(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same_record(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True), where
    else:
        assert a == b and type(a) is type(b), (where, a, b)


@pytest.mark.parametrize("which", ["seq", "lyft"])
def test_packed_records_are_the_records_the_tables_give(which: str, real_seq_root: Path,
                                                        real_lyft_root: Path, paging: str) -> None:
    """Every record `ds.samples` makes again equals, field by field, the one the reader makes from the
    tables (sweeps included: 358 on the real scene; Lyft's three LiDARs)."""
    ds = load_nuscenes(real_seq_root if which == "seq" else real_lyft_root, sweeps=True)
    assert isinstance(ds.samples, LazySamples)
    idx = R.read_tables(ds.root, ds.version, True)
    n_sweeps = 0
    for sc in ds.scenes:
        for i, tok in enumerate(sc.sample_tokens):
            want = R._sample_record(idx, tok, sc.name, i, R._prev_keys(idx, sc, i), False)
            _assert_same_record(ds.sample(tok), want, tok)
            n_sweeps += sum(len(want.sweeps_of(k)) for k in range(len(want.lidars)))
    assert len(ds.samples) == (41 if which == "seq" else 16)
    if which == "seq":
        assert n_sweeps == 358
    else:
        assert len(ds.samples[0].lidars) == 3


def test_a_placeholder_record_keeps_its_problem(real_nuscenes_root: Path, tmp_path: Path) -> None:
    import shutil

    tree = tmp_path / "ns"
    shutil.copytree(real_nuscenes_root / "v1.0-mini", tree / "v1.0-mini")
    path = tree / "v1.0-mini" / "sample_data.json"
    rows = json.loads(path.read_text())
    rows[0]["width"] = "wide"
    path.write_text(json.dumps(rows))
    s = load_nuscenes(tree).samples[0]
    assert "width is not an integer" in s.problem and np.isnan(s.cameras[0].K).all()


def test_the_dataset_holds_no_table_rows_and_a_bounded_number_of_records(real_seq_root: Path) -> None:
    """What stays after reading: the pack, not the tables (`TableIndex`, `ColumnTable`), and at most
    `LazySamples._CACHED` records however many samples were visited."""
    ds = load_nuscenes(real_seq_root, sweeps=True)
    for _ in ds.samples:
        pass
    seen: set[int] = set()
    todo: list[Any] = [ds]
    records = 0
    while todo:
        obj = todo.pop()
        if id(obj) in seen or isinstance(obj, (type, type(R))):
            continue
        seen.add(id(obj))
        assert not isinstance(obj, (R.TableIndex, ColumnTable)), type(obj)
        records += type(obj).__name__ == "SampleRecord"
        todo.extend(gc.get_referents(obj))
    assert 0 < records <= LazySamples._CACHED < len(ds.samples) or records <= len(ds.samples) < LazySamples._CACHED


def test_a_pickled_dataset_finds_its_samples_under_another_hash_seed(real_seq_root: Path, tmp_path: Path) -> None:
    """Token lookups use `hash`, which differs between processes: a dataset sent to a worker (pickled:
    its records made) indexes itself again where it lands."""
    ds = load_nuscenes(real_seq_root)
    blob = tmp_path / "ds.pkl"
    blob.write_bytes(pickle.dumps(ds.select(None)))
    token = ds.samples[17].token
    code = (f"import pickle; ds = pickle.loads(open({str(blob)!r}, 'rb').read()); "
            f"assert type(ds.samples) is tuple; print(ds.index_of({token!r}), ds.sample({token!r}).token)")
    for seed in ("1", "2"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO,
                             env={**os.environ, "PYTHONHASHSEED": seed}).stdout.split()
        assert out == ["17", token]


def test_selections_and_slices_keep_the_order_and_make_records_lazily(real_seq_root: Path) -> None:
    ds = load_nuscenes(real_seq_root)
    sub = ds.samples[5:9]
    assert isinstance(sub, LazySamples) and [s.token for s in sub] == ds.sample_tokens()[5:9]
    scene = ds.scenes[0]
    assert ds.only_scenes((scene,)).sample_tokens() == list(scene.sample_tokens)
    sliced = ds.scene_slice(scene)
    assert type(sliced.samples) is tuple and [s.token for s in sliced.samples] == list(scene.sample_tokens)
    marked = ds.with_problems({3: "planted"})
    assert marked.samples[3].problem == "planted" and not marked.samples[2].problem and not ds.samples[3].problem


def test_the_streamed_sweep_check_counts_each_sweep_once(real_seq_root: Path, tmp_path: Path) -> None:
    """Histories are walked one after the other, each compared with the previous only; the count of
    needed files equals the old definition's (every history's sweeps, deduplicated as a whole)."""
    ds = load_nuscenes(real_seq_root, sweeps=True)
    for n in (1, 3, 10):
        histories = Histories(ds, n)
        needed = {sw.token: sw.path for h in histories for sw in h}
        found = sum(p.is_file() for p in needed.values())  # the keyframes' files: the scene ships no sweeps/
        assert len(needed) > found
        with pytest.raises(OccDataError, match=rf"; {found} of the {len(needed)} sweep files needed were found"):
            check_sweep_files(histories, n)


def test_packed_boxes_travel_as_a_dict_and_tables_refuse_to(real_seq_root: Path, tmp_path: Path) -> None:
    """Boxes sent to a worker arrive as a plain dict (their index is this process's str hashes); a
    `ColumnTable` refuses to be pickled rather than arrive with a wrong index."""
    from occdata.nuscenes.annotations import PackedBoxes, load_annotations

    ann = load_annotations(real_seq_root, "v1.0-mini")
    assert isinstance(ann.boxes_by_sample, PackedBoxes) and len(ann.boxes_by_sample) == 41
    token = next(iter(ann.boxes_by_sample))
    want = [(b.token, b.center_global.tolist(), b.category) for b in ann.boxes_by_sample[token]]
    blob = tmp_path / "ann.pkl"
    blob.write_bytes(pickle.dumps(ann))
    code = (f"import pickle; a = pickle.loads(open({str(blob)!r}, 'rb').read()); b = a.boxes_by_sample; "
            f"assert type(b) is dict; print(repr([(x.token, x.center_global.tolist(), x.category) "
            f"for x in b[{token!r}]]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO,
                         env={**os.environ, "PYTHONHASHSEED": "7"}).stdout.strip()
    assert out == repr(want)
    with pytest.raises(TypeError, match="not sent to other processes"):
        pickle.dumps(load_table(real_seq_root / "v1.0-mini" / "sample.json", columns=True))


def test_the_hash_index_gives_every_candidate_in_order_and_callers_compare() -> None:
    """CPython hashes -1 and -2 alike (-2): a true 64-bit collision, by hand."""
    from occdata.nuscenes.columns import HashIndex

    assert hash(-1) == hash(-2)
    keys = [-2, 5, -1, 7]
    index = HashIndex(np.array([hash(k) for k in keys], dtype=np.int64))
    assert list(index.candidates(-1)) == [0, 2]  # both: the caller tells them apart
    assert next(p for p in index.candidates(-1) if keys[p] == -1) == 2
    assert list(index.candidates(8)) == []
    assert index.first(np.array([hash(7), hash(8), hash(-1)], dtype=np.int64)).tolist() == [3, -1, 0]
    assert HashIndex(np.zeros(0, np.int64)).first(np.array([1], dtype=np.int64)).tolist() == [-1]


def test_spilled_blobs_read_back_whole_in_any_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Blobs across the write buffer's edge, read before and after it is written; the file has no
    name (nothing left by a kill) and a spill refuses pickling."""
    import tempfile

    from occdata.nuscenes.spill import _BUFFER, Spill

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    rng = np.random.default_rng(0)
    spill = Spill()
    blobs = [rng.bytes(int(n)) for n in rng.integers(0, _BUFFER // 3, size=40)] + [b"", rng.bytes(_BUFFER + 5)]
    for k, blob in enumerate(blobs):
        spill.add(blob)
        assert spill.get(k) == blob  # the newest one, often still in the tail
        assert spill.get(k // 2) == blobs[k // 2]
    order = rng.permutation(len(blobs))
    assert [spill.get(int(k)) for k in order] == [blobs[int(k)] for k in order]
    assert len(spill) == len(blobs) and spill.nbytes() < 8 * len(blobs) + _BUFFER
    assert os.listdir(tmp_path) == []
    with pytest.raises(TypeError, match="not pickled"):
        pickle.dumps(spill)


def _buffer_bytes(root: Any) -> int:
    """Bytes of the arrays and byte buffers reachable from `root` (strings and records not counted)."""
    from array import array

    seen: set[int] = set()
    todo, total = [root], 0
    while todo:
        obj = todo.pop()
        if id(obj) in seen or isinstance(obj, (type, type(R))):
            continue
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            total += obj.nbytes if obj.base is None else 0
        elif isinstance(obj, (bytes, bytearray, array)):
            total += len(obj) * (obj.itemsize if isinstance(obj, array) else 1)
        todo.extend(gc.get_referents(obj))
    return total


def test_the_dataset_keeps_its_records_on_disk(real_seq_root: Path) -> None:
    """In memory, a sample's packed record costs its blob's end and its index entries (a few dozen
    bytes), not its ~2.4 KB of sensors: 41 samples with 358 sweeps (the calibrations are shared)."""
    ds = load_nuscenes(real_seq_root, sweeps=True)
    ds.samples._cache.clear()  # type: ignore[attr-defined]
    held = _buffer_bytes(ds)
    assert held < 48 * len(ds.samples) + 16_384, held


def test_the_boxes_stay_on_disk_until_asked_for(real_seq_root: Path) -> None:
    """In memory, a sample's boxes cost its blob's end and an index entry; each box is made when asked
    for, equal to the one the table's row gives (the real scene's boxes: ~40 a keyframe)."""
    from occdata.nuscenes.annotations import load_annotations
    from occdata.nuscenes.tables import iter_table_rows

    ann = load_annotations(real_seq_root, "v1.0-mini")
    n_boxes = sum(len(b) for b in ann.boxes_by_sample.values())
    assert n_boxes > 20 * len(ann.boxes_by_sample)
    held = _buffer_bytes(ann.boxes_by_sample)
    assert held < 48 * len(ann.boxes_by_sample) + 4096, held
    rows = {r["token"]: r for r in iter_table_rows(real_seq_root / "v1.0-mini" / "sample_annotation.json")}
    for sample in ann.boxes_by_sample:
        for b in ann.boxes_by_sample[sample]:
            row = rows[b.token]
            assert (b.instance_token, b.sample_token, b.prev, b.next) == (row["instance_token"], sample, row["prev"],
                                                                         row["next"])
            assert b.center_global.tolist() == row["translation"] and b.size_wlh.tolist() == row["size"]
            assert b.rotation_wxyz.tolist() == row["rotation"] and b.num_lidar_pts == row["num_lidar_pts"]
            assert not b.center_global.flags.writeable
