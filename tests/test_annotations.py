"""3D boxes (occdata.nuscenes.annotations) on the REAL scene-0916 tables and hand-made tracks.

Independent truth: the official devkit's `NuScenes.get_boxes` and pyquaternion's `slerp` (run in
the devkit venv, OCCDATA_DEVKIT_PYTHON), hand-computed poses, and the table rows themselves. The
real tables are read from ../shared or copied to a temp folder for damage; never into the repo.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import tracemalloc
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_SEQ, missing_fixture

from occdata.errors import OccDataError
from occdata.nuscenes import Annotations, BoxRecord, boxes_for_lidar, load_annotations, load_nuscenes, tables
from occdata.nuscenes.annotations import slerp_wxyz

needs_devkit = pytest.mark.skipif(
    not os.environ.get("OCCDATA_DEVKIT_PYTHON"),
    reason="set OCCDATA_DEVKIT_PYTHON to a python with nuscenes-devkit (scripts/devkit_env.sh)",
)

DEVKIT_GET_BOXES = r'''
import json, sys
from nuscenes import NuScenes
nusc = NuScenes(version="v1.0-mini", dataroot=sys.argv[1], verbose=False)
out = {}
for sd in nusc.sample_data:
    if sd["channel"] == "LIDAR_TOP":
        out[sd["token"]] = [
            {"token": b.token, "instance": nusc.get("sample_annotation", b.token)["instance_token"],
             "center": [float(v) for v in b.center], "wlh": [float(v) for v in b.wlh],
             "q": [float(v) for v in b.orientation.elements]}
            for b in nusc.get_boxes(sd["token"])
        ]
json.dump(out, open(sys.argv[2], "w"))
'''

DEVKIT_SLERP = r'''
import sys
import numpy as np
from pyquaternion import Quaternion
with np.load(sys.argv[1]) as f:
    q0, q1, amount = f["q0"], f["q1"], f["amount"]
out = np.array([Quaternion.slerp(Quaternion(a), Quaternion(b), t).elements for a, b, t in zip(q0, q1, amount)])
np.save(sys.argv[2], out)
'''


@pytest.fixture(scope="module")
def seq_root() -> Path:
    if not (REAL_SEQ / "v1.0-mini" / "sample_annotation.json").is_file():
        missing_fixture("real nuScenes scene", REAL_SEQ)
    return REAL_SEQ


@pytest.fixture(scope="module")
def real_ann(seq_root: Path) -> Annotations:
    return load_annotations(seq_root, "v1.0-mini")


def _rows(root: Path, table: str) -> list[dict]:
    return json.loads((root / "v1.0-mini" / f"{table}.json").read_text())


def _devkit(script: str, *args: str) -> None:
    res = subprocess.run([os.environ["OCCDATA_DEVKIT_PYTHON"], "-c", script, *args],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]


# --- real scene: contents and the devkit's get_boxes -------------------------------------------------
def test_real_boxes_are_the_table_rows(seq_root: Path, real_ann: Annotations) -> None:
    rows = _rows(seq_root, "sample_annotation")
    assert sum(map(len, real_ann.boxes_by_sample.values())) == len(rows) == 2424
    assert len(real_ann.boxes_by_sample) == 41 and len(real_ann.instance_category) == 95
    counts = Counter(real_ann.instance_category.values())
    assert (counts["vehicle.car"], counts["human.pedestrian.adult"], counts["vehicle.motorcycle"]) == (57, 23, 8)
    sample_ts = {s["token"]: s["timestamp"] for s in _rows(seq_root, "sample")}
    by_token = {b.token: b for boxes in real_ann.boxes_by_sample.values() for b in boxes}
    for row in rows[::50]:
        box = by_token[row["token"]]
        assert (box.sample_token, box.instance_token, box.num_lidar_pts) == (
            row["sample_token"], row["instance_token"], row["num_lidar_pts"])
        assert box.center_global.tolist() == row["translation"] and box.size_wlh.tolist() == row["size"]
        assert box.rotation_wxyz.tolist() == row["rotation"] and box.timestamp == sample_ts[row["sample_token"]]
    # Table order within a sample.
    order = [r["token"] for r in rows if r["sample_token"] == rows[0]["sample_token"]]
    assert [b.token for b in real_ann.boxes_by_sample[rows[0]["sample_token"]]] == order


@needs_devkit
def test_boxes_for_lidar_match_devkit_get_boxes(seq_root: Path, real_ann: Annotations, tmp_path: Path) -> None:
    """Every LIDAR_TOP sample_data of scene-0916 (41 keyframes + 358 sweeps; the reader reads the
    sweep rows although their files are not shipped)."""
    _devkit(DEVKIT_GET_BOXES, str(seq_root), str(tmp_path / "boxes.json"))
    theirs = json.loads((tmp_path / "boxes.json").read_text())
    ds = load_nuscenes(seq_root, sweeps=True)
    seen, n_boxes, n_moved = set(), 0, 0
    worst_c = worst_q = 0.0
    for i, sample in enumerate(ds.samples):
        for lidar in (sample.lidar, *sample.sweeps):
            ours, ref = boxes_for_lidar(real_ann, ds, i, lidar), theirs[lidar.token]
            assert [b.token for b in ours] == [r["token"] for r in ref], lidar.token
            for b, r in zip(ours, ref, strict=True):
                assert b.instance_token == r["instance"] and b.size_wlh.tolist() == r["wlh"]
                worst_c = max(worst_c, float(np.abs(b.center_global - r["center"]).max()))
                worst_q = max(worst_q, float(np.abs(b.rotation_wxyz - r["q"]).max()))
                assert b.timestamp == lidar.timestamp
                stored = real_ann.boxes_by_sample[b.sample_token]
                n_moved += not any(s.token == b.token and np.array_equal(s.center_global, b.center_global)
                                   for s in stored)
            n_boxes += len(ours)
            seen.add(lidar.token)
    assert seen == set(theirs) and len(seen) == 399
    print(f"\nget_boxes: {n_boxes} boxes over 399 LIDAR_TOP records, {n_moved} interpolated; "
          f"max |d centre| {worst_c:.2e} m, max |d q| {worst_q:.2e}")
    assert worst_c < 1e-6 and worst_q < 1e-9 and n_moved > 10_000


@needs_devkit
def test_slerp_matches_pyquaternion(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    n = 400
    q0 = rng.normal(size=(n, 4))
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q0 + rng.normal(scale=rng.choice([1e-4, 1e-2, 0.5, 3.0], size=(n, 1)), size=(n, 4))
    q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
    q1[::3] *= -1  # the shorter-arc rule
    q0[::7] *= 1 + 1e-9  # nearly unit inputs (pyquaternion's Pade normalisation)
    q1[::11] *= 1.5  # far from unit
    amount = rng.uniform(-0.2, 1.2, size=n)  # clipped to [0, 1]
    np.savez(tmp_path / "in.npz", q0=q0, q1=q1, amount=amount)
    _devkit(DEVKIT_SLERP, str(tmp_path / "in.npz"), str(tmp_path / "out.npy"))
    theirs = np.load(tmp_path / "out.npy", allow_pickle=False)
    ours = np.array([slerp_wxyz(a, b, t) for a, b, t in zip(q0, q1, amount, strict=True)])
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12)


def test_boxes_for_lidar_on_real_sweeps_without_devkit(seq_root: Path, real_ann: Annotations) -> None:
    """Sweeps are interpolated between their sample's `prev` and the sample (timestamps from the
    tables): a sweep half-way in time puts a box half-way between its two annotations."""
    ds = load_nuscenes(seq_root, check_files=True, sweeps=True)
    i = 10
    sample, prev = ds.samples[i], ds.samples[i - 1]
    keyframe = boxes_for_lidar(real_ann, ds, i, sample.lidar)
    def fields(boxes):  # records are made when asked: compared by value
        return [(b.token, b.center_global.tolist(), b.rotation_wxyz.tolist(), b.timestamp) for b in boxes]

    assert fields(keyframe) == fields(real_ann.boxes_by_sample[sample.token])  # the stored boxes, as stored
    prev_of = {b.instance_token: b for b in real_ann.boxes_by_sample[prev.token]}
    for sw in sample.sweeps:
        assert sw.sample_token == sample.token  # nuScenes files a sweep under the NEXT keyframe
        frac = (sw.timestamp - prev.timestamp) / (sample.timestamp - prev.timestamp)
        boxes = boxes_for_lidar(real_ann, ds, i, sw)
        assert [b.token for b in boxes] == [b.token for b in keyframe]
        for b, k in zip(boxes, keyframe, strict=True):
            p = prev_of.get(k.instance_token)
            expect = k.center_global if p is None else p.center_global + frac * (k.center_global - p.center_global)
            np.testing.assert_allclose(b.center_global, expect, rtol=0, atol=1e-9)
    # The first keyframe's sweeps precede a sample without prev: boxes as stored, at the sweep time.
    first = ds.samples[0]
    for sw in first.sweeps:
        boxes = boxes_for_lidar(real_ann, ds, 0, sw)
        assert [b.token for b in boxes] == [b.token for b in real_ann.boxes_by_sample[first.token]]
    with pytest.raises(OccDataError, match="neither the LIDAR_TOP keyframe nor a sweep") as info:
        boxes_for_lidar(real_ann, ds, i, ds.samples[i + 1].sweeps[0])
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("spilled", [False, True])
def test_identical_duplicate_is_kept_once_and_arrays_are_read_only(seq_root: Path, tmp_path: Path, spilled: bool,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    if spilled:
        monkeypatch.setattr(tables, "_SET_IN_MEMORY", 3)
    root = _copy_tables(seq_root, tmp_path)
    _edit(root, "sample_annotation", lambda rows: rows.append(dict(rows[5])))
    ann = load_annotations(root, "v1.0-mini")
    assert sum(map(len, ann.boxes_by_sample.values())) == 2424
    box = next(iter(ann.boxes_by_sample.values()))[0]
    for arr in (box.center_global, box.size_wlh, box.rotation_wxyz):
        assert arr.dtype == np.float64 and not arr.flags.writeable


def test_subset_of_samples(seq_root: Path, real_ann: Annotations) -> None:
    ds = load_nuscenes(seq_root)
    keep = {s.token for s in ds.samples[3:6]}
    part = load_annotations(seq_root, "v1.0-mini", sample_tokens=keep)
    assert set(part.boxes_by_sample) == keep
    for tok in keep:
        assert [b.token for b in part.boxes_by_sample[tok]] == [b.token for b in real_ann.boxes_by_sample[tok]]


# --- hand-made tracks -------------------------------------------------------------------------------
def _box(token: str, inst: str, sample: str, center: list[float], yaw_deg: float, ts: int) -> BoxRecord:
    half = np.radians(yaw_deg) / 2
    return BoxRecord(token=token, instance_token=inst, sample_token=sample, category="vehicle.car",
                     center_global=np.array(center, float), size_wlh=np.array([2.0, 4.0, 1.5]),
                     rotation_wxyz=np.array([np.cos(half), 0, 0, np.sin(half)]), timestamp=ts, num_lidar_pts=10)


def test_hand_made_interpolation() -> None:
    ann = Annotations(
        boxes_by_sample={
            "s0": (_box("a0", "A", "s0", [0, 0, 0], 0, 1_000_000), _box("c0", "C", "s0", [5, 5, 0], 0, 1_000_000)),
            "s1": (_box("a1", "A", "s1", [10, 4, 2], 90, 1_500_000), _box("b1", "B", "s1", [1, 2, 3], 30, 1_500_000)),
        },
        instance_category={"A": "vehicle.car", "B": "vehicle.car", "C": "vehicle.car"},
    )
    assert ann.boxes_at("s1", "", 0, 0, 1_200_000) == ann.boxes_by_sample["s1"]  # keyframe: as stored
    a, b = ann.boxes_at("s1", "s0", 1_000_000, 1_500_000, 1_250_000)  # C (only in s0) is dropped
    assert (a.token, b.token, a.timestamp, b.timestamp) == ("a1", "b1", 1_250_000, 1_250_000)
    np.testing.assert_allclose(a.center_global, [5, 2, 1], atol=1e-12)
    np.testing.assert_allclose(a.rotation_wxyz, [np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)], atol=1e-12)
    assert b.center_global.tolist() == [1, 2, 3] and b.rotation_wxyz is ann.boxes_by_sample["s1"][1].rotation_wxyz
    # The box frame: x along the length. Yaw 45 deg: the front face centre is 2 m along (1, 1)/sqrt 2.
    front = a.T_global_from_box() @ [2.0, 0, 0, 1]
    np.testing.assert_allclose(front[:3], [5 + np.sqrt(2), 2 + np.sqrt(2), 1], atol=1e-12)
    # Times outside [t0, t1] clamp; the box keeps the requested time.
    (late, _) = ann.boxes_at("s1", "s0", 1_000_000, 1_500_000, 9_000_000)
    np.testing.assert_allclose(late.center_global, [10, 4, 2], atol=0)
    assert late.timestamp == 9_000_000
    # A sign-flipped quaternion is the same rotation: the shorter arc gives the same pose.
    a1 = ann.boxes_by_sample["s1"][0]
    flipped = dataclasses.replace(a1, rotation_wxyz=-a1.rotation_wxyz)
    ann2 = Annotations({"s0": ann.boxes_by_sample["s0"], "s1": (flipped,)}, ann.instance_category)
    (a2,) = ann2.boxes_at("s1", "s0", 1_000_000, 1_500_000, 1_250_000)
    np.testing.assert_allclose(a2.T_global_from_box(), a.T_global_from_box(), atol=1e-12)
    with pytest.raises(OccDataError, match="is not after its prev"):
        ann.boxes_at("s1", "s0", 1_500_000, 1_500_000, 1_500_000)
    assert ann.boxes_at("nothing", "s0", 0, 1, 0) == ()


# --- broken tables ----------------------------------------------------------------------------------
def _copy_tables(src: Path, dst: Path) -> Path:
    shutil.copytree(src / "v1.0-mini", dst / "v1.0-mini")
    return dst


def _edit(root: Path, table: str, fn) -> None:
    path = root / "v1.0-mini" / f"{table}.json"
    rows = json.loads(path.read_text())
    fn(rows)
    path.write_text(json.dumps(rows))


def _mid_track(rows: list[dict]) -> dict:
    return next(r for r in rows if r["prev"] and r["next"])


BROKEN = {
    "prev_dangling": ("sample_annotation", lambda rows: _mid_track(rows).update(prev="f" * 32),
                      "prev 'ffffffffffffffffffffffffffffffff' is not in sample_annotation.json"),
    "next_dangling": ("sample_annotation", lambda rows: _mid_track(rows).update(next="e" * 32),
                      "next 'eeeeeeeeeeeeeeeeeeeeeeeeeeeeeeee' is not in sample_annotation.json"),
    "next_disagrees": ("sample_annotation", lambda rows: _mid_track(rows).update(next=_mid_track(rows)["prev"]),
                       "but that row's prev is"),
    "prev_other_instance": ("sample_annotation",
                            lambda rows: _mid_track(rows).update(prev=next(
                                r["token"] for r in rows if r["instance_token"] != _mid_track(rows)["instance_token"])),
                            "is a box of another instance"),
    "sample_dangling": ("sample_annotation", lambda rows: rows[5].update(sample_token="d" * 32),
                        "refers to sample 'dddddddddddddddddddddddddddddddd', not in sample.json"),
    "instance_dangling": ("sample_annotation", lambda rows: rows[5].update(instance_token="c" * 32),
                          "refers to instance 'cccccccccccccccccccccccccccccccc', not in instance.json"),
    "category_dangling": ("instance", lambda rows: rows[3].update(category_token="b" * 32),
                          "refers to category 'bbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbb', not in category.json"),
    "size_text": ("sample_annotation", lambda rows: rows[5].update(size="big"), "size is not numeric ('big')"),
    "size_null": ("sample_annotation", lambda rows: rows[5].update(size=[1.0, None, 2.0]),
                  "size [1.0, nan, 2.0] is not finite"),
    "size_zero": ("sample_annotation", lambda rows: rows[5].update(size=[1.0, 0.0, 2.0]), "is not positive"),
    "rotation_short": ("sample_annotation", lambda rows: rows[5].update(rotation=[1, 0, 0]),
                       "rotation has shape (3,), expected 4 values"),
    "rotation_not_unit": ("sample_annotation", lambda rows: rows[5].update(rotation=[2, 0, 0, 0]),
                          "is not a unit quaternion"),
    "translation_text": ("sample_annotation", lambda rows: rows[5].update(translation=["1", "2", "3"]),
                         "translation is not numeric"),
    "no_size_field": ("sample_annotation", lambda rows: rows[5].pop("size"), "has no field 'size'"),
    "num_pts_text": ("sample_annotation", lambda rows: rows[5].update(num_lidar_pts="many"),
                     "num_lidar_pts is not an integer ('many')"),
    "duplicate_differs": ("sample_annotation", lambda rows: rows.append({**rows[5], "size": [9.0, 9.0, 9.0]}),
                          "appears twice with different content"),
}


@pytest.mark.parametrize("spilled", [False, True])
@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_tables_are_one_line_errors(seq_root: Path, tmp_path: Path, case: str, spilled: bool,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The same errors with the tables' token sets held or spilled to disk (as past 2**18 rows)."""
    if spilled:
        monkeypatch.setattr(tables, "_SET_IN_MEMORY", 3)
    table, fn, message = BROKEN[case]
    root = _copy_tables(seq_root, tmp_path)
    _edit(root, table, fn)
    with pytest.raises(OccDataError) as info:
        load_annotations(root, "v1.0-mini")
    msg = str(info.value)
    assert "\n" not in msg and message in msg, msg
    assert ("sample_annotation" in msg or "instance" in msg) and "'" in msg  # names the table and the token


def test_missing_annotation_tables(seq_root: Path, tmp_path: Path) -> None:
    root = _copy_tables(seq_root, tmp_path)
    (root / "v1.0-mini" / "instance.json").unlink()
    with pytest.raises(OccDataError, match="missing table: .*instance.json"):
        load_annotations(root, "v1.0-mini")
    (root / "v1.0-mini" / "sample_annotation.json").unlink()  # a test split: no annotations at all
    ann = load_annotations(root, "v1.0-mini")
    assert ann.boxes_by_sample == {} and ann.instance_category == {}
    for table in ("instance", "sample_annotation"):  # the official test split ships them empty
        (root / "v1.0-mini" / f"{table}.json").write_text("[]")
    ann = load_annotations(root, "v1.0-mini")
    assert ann.boxes_by_sample == {} and ann.instance_category == {}
    ds = load_nuscenes(root, sweeps=True)
    assert boxes_for_lidar(ann, ds, 3, ds.samples[3].sweeps[0]) == ()


def test_the_first_broken_row_is_named_first(seq_root: Path, tmp_path: Path) -> None:
    """Faults found bucket by bucket are named in row order, prev before next within a row."""
    root = _copy_tables(seq_root, tmp_path)

    def two_faults(rows: list[dict]) -> None:
        mids = [r for r in rows if r["prev"] and r["next"]]
        mids[-1].update(prev="f" * 32)  # a late row
        mids[3].update(next="e" * 32, prev="d" * 32)  # an earlier row, both links broken

    _edit(root, "sample_annotation", two_faults)
    with pytest.raises(OccDataError, match=f"prev '{'d' * 32}' is not in sample_annotation.json"):
        load_annotations(root, "v1.0-mini")


def test_boxes_hashes_are_held_on_disk(monkeypatch: pytest.MonkeyPatch) -> None:
    """100,000 boxes: the hashes their checks need (5 a box) were 40 bytes a box in memory (4 MB); now
    in bucket files, and memory keeps 8 bytes a box (its blob's end) and the files' write buffers (made
    small here: they are constants)."""
    from occdata.nuscenes import annotations, spill

    monkeypatch.setattr(annotations, "_BUCKET_ROWS", 2048)
    monkeypatch.setattr(spill, "_BUFFER", 1 << 16)
    monkeypatch.setattr(tables, "_SET_IN_MEMORY", 4096)
    samples = {f"s{i}": {"timestamp": 1_000_000 + i} for i in range(1000)}
    reader = annotations._BoxReader(samples, {f"i{i}": "car" for i in range(1000)})  # type: ignore[arg-type]
    n, chunk = 100_000, 10_000
    rows = [[{"token": f"t{k}", "sample_token": f"s{k % 1000}", "instance_token": f"i{k % 1000}",
              "translation": [1.0, 2.0, 3.0], "size": [1.0, 2.0, 1.5], "rotation": [1.0, 0.0, 0.0, 0.0],
              "num_lidar_pts": 3, "prev": "", "next": ""} for k in range(c0, c0 + chunk)] for c0 in range(0, n, chunk)]
    reader._add(rows[0])  # the buffers and caches made once
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    for part in rows[1:]:
        reader._add(part)
    held = tracemalloc.get_traced_memory()[0] - base
    tracemalloc.stop()
    assert held < 8 * n + 600_000, held  # before: > 40 * n
    boxes = reader.packed()
    assert len(boxes) == 1000 and len(boxes["s7"]) == n // 1000
    assert [b.token for b in boxes["s7"][:3]] == ["t7", "t1007", "t2007"]
