"""Issue #12, input side: bad tables, paths, tokens, labels folders and images never give a silently
wrong store, a file read outside the root, or a traceback. Small synthetic worlds (2 scenes x 3).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.store.layout import STATE_DONE, STATE_ERROR
from occdata.store.reader import open_store


def clone_world(src: Path, dst: Path, labels: bool = True) -> Path:
    """Tables copied (so they can be broken); sensor files and labels linked, never copied."""
    shutil.copytree(src / "v1.0-mini", dst / "v1.0-mini")
    dirs = ["samples"] + (["gts"] if labels else [])
    for d in dirs:
        for f in (src / d).rglob("*"):
            if f.is_file():
                target = dst / f.relative_to(src)
                target.parent.mkdir(parents=True, exist_ok=True)
                target.symlink_to(f.resolve())
    return dst


def edit_table(root: Path, table: str, fn: Callable[[list[dict[str, Any]]], Any]) -> None:
    path = root / "v1.0-mini" / f"{table}.json"
    rows = json.loads(path.read_text())
    fn(rows)
    path.write_text(json.dumps(rows))


def rows_of(root: Path, table: str) -> list[dict[str, Any]]:
    return json.loads((root / "v1.0-mini" / f"{table}.json").read_text())


def cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


def one_error_line(code: int, output: str, *needles: str) -> str:
    assert code == 1, output
    lines = [ln for ln in output.splitlines() if ln.strip() and not ln.startswith(("labels:", "warning:"))]
    assert len(lines) == 1 and lines[0].startswith("Error: "), output
    assert "Traceback" not in output
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def build(root: Path, out: Path, *extra: str) -> tuple[int, str]:
    return cli("build", "--root", str(root), "--out", str(out), "--no-progress", *extra)


@pytest.fixture
def world(synth_root: Path, tmp_path: Path) -> Path:
    return clone_world(synth_root, tmp_path / "w")


def _cam_row(root: Path, sample_index: int = 1, channel: str = "CAM_BACK") -> tuple[list[dict], dict]:
    """The sample_data row of one keyframe camera of the sample_index-th sample in sample.json."""
    rows = rows_of(root, "sample_data")
    tok = rows_of(root, "sample")[sample_index]["token"]
    row = next(r for r in rows if r["sample_token"] == tok and f"/{channel}/" in r["filename"] and r["is_key_frame"])
    return rows, row


# --- 1. corrupt JPEGs that libjpeg papers over --------------------------------------------------------
def _sos_end(data: bytes) -> int:
    i = 2
    while True:
        seg = int.from_bytes(data[i + 2 : i + 4], "big")
        if data[i + 1] == 0xDA:
            return i + 2 + seg
        i += 2 + seg


def _damage(data: bytes, kind: str) -> bytes:
    start = _sos_end(data)
    if kind == "truncated_with_eoi":
        return data[: len(data) // 2] + b"\xff\xd9"
    if kind == "entropy_zeroed":
        return data[:start] + bytes(len(data) - start - 2) + b"\xff\xd9"
    if kind == "entropy_partly_zeroed":
        mid = start + (len(data) - start) // 3
        return data[:mid] + bytes(len(data) // 4) + data[mid + len(data) // 4 :]
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["truncated_with_eoi", "entropy_zeroed", "entropy_partly_zeroed"])
@pytest.mark.parametrize("scale", ["1.0", "0.5"])
def test_jpeg_with_decoder_warning_is_corrupt(world: Path, tmp_path: Path, kind: str, scale: str) -> None:
    rows, row = _cam_row(world)
    victim = world / row["filename"]
    bad = _damage(victim.resolve().read_bytes(), kind)
    victim.unlink()
    victim.write_bytes(bad)
    line = one_error_line(*build(world, tmp_path / "s.zarr", "--image-scale", scale), "corrupt JPEG", victim.name)
    assert "Corrupt JPEG data" in line or "Premature end" in line
    # skip: the sample is recorded as failed (never stored as done with grey rows), the rest is done
    code, out = build(world, tmp_path / "k.zarr", "--image-scale", scale, "--on-error", "skip")
    assert code == 0, out
    state = open_store(tmp_path / "k.zarr").state
    assert state[1] == STATE_ERROR and (np.delete(state, 1) == STATE_DONE).all()


def test_jpeg_with_decoder_warning_is_corrupt_in_worker_processes(world: Path, tmp_path: Path) -> None:
    _, row = _cam_row(world)
    victim = world / row["filename"]
    bad = _damage(victim.resolve().read_bytes(), "truncated_with_eoi")
    victim.unlink()
    victim.write_bytes(bad)
    code, out = build(world, tmp_path / "k.zarr", "--workers", "2", "--on-error", "skip")
    assert code == 0, out
    reader = open_store(tmp_path / "k.zarr")
    assert reader.state[1] == STATE_ERROR and (np.delete(reader.state, 1) == STATE_DONE).all()
    (err,) = reader.attrs["errors"]
    assert victim.name in err["reason"] and "Corrupt JPEG data" in err["reason"]


def test_decoder_warning_is_captured_and_stderr_restored(synth_root: Path, capfd: pytest.CaptureFixture) -> None:
    import cv2

    from occdata.sensors.jpeg_check import decode_jpeg_checked

    good = next((synth_root / "samples" / "CAM_FRONT").glob("*.jpg")).read_bytes()
    img, warning = decode_jpeg_checked(_damage(good, "truncated_with_eoi"), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    assert img is not None and "Corrupt JPEG data" in warning  # the image comes back; the warning tells
    img, warning = decode_jpeg_checked(good, cv2.IMREAD_COLOR)
    assert img is not None and warning == ""
    os.write(2, b"stderr works\n")
    assert capfd.readouterr().err == "stderr works\n"  # nothing leaked, fd 2 restored


# --- 2. duplicate tokens -------------------------------------------------------------------------------
def _dup_changed(table: str) -> Callable[[list[dict]], None]:
    def fn(rows: list[dict]) -> None:
        row = dict(rows[0])
        if "translation" in row:
            row["translation"] = [row["translation"][0] + 5.0, *row["translation"][1:]]
        elif table == "sample":
            row["timestamp"] += 1
        else:
            row["description"] = row.get("description", "") + " (edited)"
        rows.append(row)
    return fn


@pytest.mark.parametrize("table", ["calibrated_sensor", "sample", "ego_pose", "scene"])
def test_duplicate_token_with_other_content_is_an_error(world: Path, tmp_path: Path, table: str) -> None:
    token = rows_of(world, table)[0]["token"]
    edit_table(world, table, _dup_changed(table))
    one_error_line(*cli("scan", "--root", str(world)), "duplicate token", f"{table}.json", token)
    one_error_line(*build(world, tmp_path / "s.zarr"), "duplicate token", f"{table}.json", token)


def test_identical_duplicate_rows_are_tolerated_with_a_warning(world: Path, tmp_path: Path) -> None:
    edit_table(world, "calibrated_sensor", lambda rows: rows.append(dict(rows[0])))
    code, out = cli("scan", "--root", str(world))
    assert code == 0, out
    assert "warning: calibrated_sensor.json: 1 identical duplicate" in out
    code, out = build(world, tmp_path / "s.zarr")
    assert code == 0 and "warning: calibrated_sensor.json" in out, out


# --- 3. tokens of any length and alphabet ----------------------------------------------------------------
def _retoken(root: Path, new: Callable[[str], str]) -> dict[str, str]:
    """Replace every token (32 hex chars) in every table, consistently; returns old -> new."""
    mapping: dict[str, str] = {}

    def sub(v: Any) -> Any:
        if isinstance(v, str) and len(v) == 32 and all(c in "0123456789abcdef" for c in v):
            return mapping.setdefault(v, new(v))
        if isinstance(v, list):
            return [sub(x) for x in v]
        return v

    for f in sorted((root / "v1.0-mini").glob("*.json")):
        rows = json.loads(f.read_text())
        f.write_text(json.dumps([{k: sub(v) for k, v in r.items()} for r in rows], ensure_ascii=False))
    return mapping


@pytest.mark.parametrize("style", ["uuid36", "non_ascii", "long_80"])
def test_tokens_are_stored_losslessly(synth_root: Path, tmp_path: Path, style: str) -> None:
    world = clone_world(synth_root, tmp_path / "w", labels=False)
    make = {
        "uuid36": lambda t: str(uuid.UUID(t)),  # 36 characters, the 32-byte prefix collides across rows
        "non_ascii": lambda t: "é-" + t[:8] + "-日本",
        "long_80": lambda t: "x" * 48 + t,
    }[style]
    mapping = _retoken(world, make)
    code, out = build(world, tmp_path / "s.zarr")
    assert code == 0, out
    reader = open_store(tmp_path / "s.zarr")
    samples = rows_of(world, "sample")
    stored = [reader.token(i) for i in range(reader.n_samples)]
    assert sorted(stored) == sorted(s["token"] for s in samples)
    # camera tokens: every one stored whole and distinct
    from occdata.store.layout import token_str

    cam = reader.small("cam/token")
    cam_tokens = {token_str(cam[i, c]) for i in range(reader.n_samples) for c in range(6)}
    assert len(cam_tokens) == 6 * reader.n_samples
    assert cam_tokens <= set(mapping.values())
    code, out = cli("verify", "--store", str(tmp_path / "s.zarr"), "--no-progress")
    assert code == 0, out


@pytest.mark.parametrize("table", ["calibrated_sensor", "sample"])
@pytest.mark.parametrize("bad", ["", "ab\u0000cd", "../../evil", "a\\b", ".."])
def test_token_that_is_not_a_file_name_is_refused(world: Path, tmp_path: Path, bad: str, table: str) -> None:
    """Tokens name folders (gts/<scene>/<token>/, prediction output): they must be one path component."""
    old = rows_of(world, table)[0]["token"]
    _retoken(world, lambda t: bad if t == old else t)
    needles = (f"{table}.json", "not usable as a file name")
    one_error_line(*cli("scan", "--root", str(world)), *needles)
    one_error_line(*build(world, tmp_path / "s.zarr"), *needles)


# --- 4. the labels folder ---------------------------------------------------------------------------------
def test_wrong_gts_fails_showing_the_expected_layout(world: Path, tmp_path: Path) -> None:
    sample = rows_of(world, "sample")[0]["token"]
    line = one_error_line(*build(world, tmp_path / "s.zarr", "--gts", str(world / "samples")),
                          "no label file", "<scene name>/<sample token>/labels.npz", "<sample token>/labels.npz")
    assert f"{sample}/labels.npz" in line  # one expected path, spelled out
    assert not (tmp_path / "s.zarr").exists()


def test_flat_labels_layout_is_accepted(world: Path, tmp_path: Path) -> None:
    flat = tmp_path / "flat"
    for f in (world / "gts").glob("*/*/labels.npz"):
        (flat / f.parent.name).mkdir(parents=True)
        (flat / f.parent.name / "labels.npz").symlink_to(f.resolve())
    code, out = build(world, tmp_path / "flat.zarr", "--gts", str(flat))
    assert code == 0, out
    assert "6 labelled" in out
    nested = open_store(tmp_path / "flat.zarr").sample_arrays(0, ("labels/semantics",))["labels/semantics"]
    code, out = build(world, tmp_path / "nested.zarr", "--gts", str(world / "gts"))
    assert code == 0, out
    ref = open_store(tmp_path / "nested.zarr").sample_arrays(0, ("labels/semantics",))["labels/semantics"]
    assert np.array_equal(nested, ref)


def test_real_occ3d_example_folder_is_read_as_flat_layout(real_nuscenes_root: Path, real_occ3d_label_dir: Path,
                                                          tmp_path: Path) -> None:
    """`../shared/data/occ3d-label/<token>/labels.npz` is the flat layout. Its sample's sensor data
    is not shipped, so the real keyframe is given that token; the stored semantics must be the file's."""
    (label_dir,) = [p for p in real_occ3d_label_dir.iterdir() if p.is_dir()]
    tree = tmp_path / "ns"
    shutil.copytree(real_nuscenes_root / "v1.0-mini", tree / "v1.0-mini")
    (tree / "samples").symlink_to(real_nuscenes_root.resolve() / "samples")
    old = rows_of(tree, "sample")[0]["token"]
    _retoken(tree, lambda t: label_dir.name if t == old else t)
    code, out = build(tree, tmp_path / "s.zarr", "--gts", str(real_occ3d_label_dir))
    assert code == 0, out
    assert "1 labelled" in out
    with np.load(label_dir / "labels.npz") as npz:
        want = npz["semantics"]
    got = open_store(tmp_path / "s.zarr").sample_arrays(0, ("labels/semantics",))["labels/semantics"]
    assert np.array_equal(got, want)


def test_labels_npz_that_is_a_folder_is_an_error(world: Path, tmp_path: Path) -> None:
    victim = next((world / "gts").glob("*/*/labels.npz"))
    victim.unlink()
    victim.mkdir()
    one_error_line(*build(world, tmp_path / "s.zarr"), "bad labels", str(victim), "folder")
    code, out = build(world, tmp_path / "k.zarr", "--on-error", "skip")
    assert code == 0, out
    reader = open_store(tmp_path / "k.zarr")
    assert (reader.state == STATE_ERROR).sum() == 1
    assert victim.parent.name in [e["token"] for e in reader.attrs["errors"]]


# --- 5. scenes that silently shrink -----------------------------------------------------------------------
def test_blank_first_sample_token_is_reported(world: Path, tmp_path: Path) -> None:
    def fn(rows: list[dict]) -> None:
        rows[0]["first_sample_token"] = ""

    edit_table(world, "scene", fn)
    name = rows_of(world, "scene")[0]["name"]
    one_error_line(*cli("scan", "--root", str(world)), name, "only 0 of its 3 samples", "nbr_samples 3")
    one_error_line(*build(world, tmp_path / "s.zarr"), name, "only 0 of its 3 samples")


def test_cut_next_chain_is_reported(world: Path, tmp_path: Path) -> None:
    samples = rows_of(world, "sample")
    first = rows_of(world, "scene")[0]["first_sample_token"]

    def cut(rows: list[dict]) -> None:
        row = next(r for r in rows if r["token"] == first)
        row["next"] = ""

    def relast(rows: list[dict]) -> None:  # make the cut consistent, so only the count shows it
        rows[0]["last_sample_token"] = first

    edit_table(world, "sample", cut)
    edit_table(world, "scene", relast)
    assert len(samples) == 6
    one_error_line(*cli("scan", "--root", str(world)), "only 1 of its 3 samples")


def test_nbr_samples_disagreeing_is_a_warning(world: Path) -> None:
    def fn(rows: list[dict]) -> None:
        rows[0]["nbr_samples"] = 40

    edit_table(world, "scene", fn)
    code, out = cli("scan", "--root", str(world))
    assert code == 0, out
    assert "nbr_samples is 40 but the tables hold 3 samples" in out


# --- 8. paths from tables stay inside their root -------------------------------------------------------
@pytest.mark.parametrize("how", ["dotdot", "absolute"])
def test_sensor_path_outside_root_is_refused(world: Path, tmp_path: Path, how: str) -> None:
    outside = tmp_path / "secret.jpg"
    _, row = _cam_row(world)
    shutil.copy((world / row["filename"]).resolve(), outside)  # a valid image: it would be stored
    rel = os.path.relpath(outside, world) if how == "dotdot" else str(outside)

    def fn(rows: list[dict]) -> None:
        next(r for r in rows if r["token"] == row["token"])["filename"] = rel

    edit_table(world, "sample_data", fn)
    one_error_line(*build(world, tmp_path / "s.zarr"), row["token"], "outside")
    one_error_line(*cli("scan", "--root", str(world)), row["token"], "outside")
    code, out = build(world, tmp_path / "k.zarr", "--on-error", "skip")
    assert code == 0, out
    reader = open_store(tmp_path / "k.zarr")
    assert reader.state[1] == STATE_ERROR and (np.delete(reader.state, 1) == STATE_DONE).all()
    secret = outside.read_bytes()
    assert secret not in b"".join(b for i in reader.done_indices() for b in reader.jpeg_bytes(i))


def test_lidar_path_outside_root_is_refused(world: Path, tmp_path: Path) -> None:
    rows = rows_of(world, "sample_data")
    row = next(r for r in rows if "/LIDAR_TOP/" in r["filename"] and r["is_key_frame"])
    row["filename"] = "samples/../../" + "x" * 3 + ".pcd.bin"
    (world / "v1.0-mini" / "sample_data.json").write_text(json.dumps(rows))
    one_error_line(*build(world, tmp_path / "s.zarr"), row["token"], "outside")


def test_scene_name_escaping_the_labels_folder_is_refused(world: Path, tmp_path: Path) -> None:
    # A labels file planted outside gts/ where "../<name>" would lead.
    scene = rows_of(world, "scene")[0]
    sample = scene["first_sample_token"]
    planted = world / "planted" / sample
    planted.mkdir(parents=True)
    (planted / "labels.npz").symlink_to(next((world / "gts").glob(f"*/{sample}/labels.npz")).resolve())

    def fn(rows: list[dict]) -> None:
        rows[0]["name"] = "../planted"

    edit_table(world, "scene", fn)
    one_error_line(*build(world, tmp_path / "s.zarr", "--gts", str(world / "gts")), "../planted",
                   "not usable as a folder name")
    one_error_line(*cli("scan", "--root", str(world)), "../planted", "not usable as a folder name")


def test_label_paths_are_confined_even_for_records_built_in_code(world: Path, tmp_path: Path) -> None:
    """Defence in depth: `find_label_files` refuses a path leaving gts/ for records that did not
    come through the table reader (the sample fails, naming it)."""
    import dataclasses

    from occdata.nuscenes import load_nuscenes
    from occdata.store.build import find_label_files

    ds = load_nuscenes(world)
    evil = dataclasses.replace(ds.samples[0], scene_name="..")
    ds = type(ds)(ds.root, ds.version, ds.scenes, (evil, *ds.samples[1:]), ds.warnings)
    paths, checked = find_label_files(world / "gts", ds, required=True)
    assert paths[0] is None and "outside" in checked.samples[0].problem
    assert all(p is not None for p in paths[1:]) and not any(s.problem for s in checked.samples[1:])


# --- 10. table values that are not numbers, and sensor files that are not files ---------------------------
def _break_value(kind: str, world: Path) -> tuple[str, str]:
    """Break one value that only sample 1 uses; returns (table, token) the error must name."""
    rows, row = _cam_row(world)
    if kind in ("width_null", "timestamp_text"):
        key, value = ("width", None) if kind == "width_null" else ("timestamp", "soon")
        row[key] = value
        (world / "v1.0-mini" / "sample_data.json").write_text(json.dumps(rows))
        return "sample_data", row["token"]
    if kind == "sample_timestamp_text":
        tok = rows_of(world, "sample")[1]["token"]
        edit_table(world, "sample", lambda rs: next(r for r in rs if r["token"] == tok).update(timestamp="soon"))
        return "sample", tok
    # calibration / pose values: give sample 1's CAM_BACK its own calibrated_sensor or ego_pose row
    if kind in ("intrinsic_text", "rotation_3"):
        cs = next(r for r in rows_of(world, "calibrated_sensor") if r["token"] == row["calibrated_sensor_token"])
        new = dict(cs, token=hashlib.md5(b"cs").hexdigest())
        if kind == "intrinsic_text":
            new["camera_intrinsic"] = "abc"
        else:
            new["rotation"] = new["rotation"][:3]
        edit_table(world, "calibrated_sensor", lambda rs: rs.append(new))
        row["calibrated_sensor_token"] = new["token"]
        (world / "v1.0-mini" / "sample_data.json").write_text(json.dumps(rows))
        return "calibrated_sensor", new["token"]
    if kind == "translation_text":
        tok = row["ego_pose_token"]
        edit_table(world, "ego_pose", lambda rs: next(r for r in rs if r["token"] == tok).update(
            translation=["a", "b", "c"]))
        return "ego_pose", tok
    raise ValueError(kind)


@pytest.mark.parametrize(
    "kind", ["width_null", "timestamp_text", "sample_timestamp_text", "intrinsic_text", "rotation_3",
             "translation_text"])
def test_unusable_table_value_is_one_line_and_skippable(world: Path, tmp_path: Path, kind: str) -> None:
    table, token = _break_value(kind, world)
    line = one_error_line(*build(world, tmp_path / "s.zarr"), table, token)
    assert "NaN" not in line  # a 3-element rotation is not misreported as NaN
    one_error_line(*cli("scan", "--root", str(world)), table, token)
    code, out = build(world, tmp_path / "k.zarr", "--on-error", "skip")
    assert code == 0, out
    state = open_store(tmp_path / "k.zarr").state
    assert state[1] == STATE_ERROR and (np.delete(state, 1) == STATE_DONE).all()


@pytest.mark.parametrize("kind", ["folder", "symlink_loop"])
@pytest.mark.parametrize("channel", ["CAM_BACK", "LIDAR_TOP"])
def test_sensor_file_that_is_not_a_file(world: Path, tmp_path: Path, kind: str, channel: str) -> None:
    _, row = _cam_row(world, channel=channel)
    victim = world / row["filename"]
    victim.unlink()
    if kind == "folder":
        victim.mkdir()
    else:
        loop = victim.with_name("loop_b")
        victim.symlink_to(loop)
        loop.symlink_to(victim)
    one_error_line(*build(world, tmp_path / "s.zarr"), victim.name)
    one_error_line(*cli("scan", "--root", str(world)), victim.name)
    code, out = build(world, tmp_path / "k.zarr", "--on-error", "skip")
    assert code == 0, out
    state = open_store(tmp_path / "k.zarr").state
    assert state[1] == STATE_ERROR and (np.delete(state, 1) == STATE_DONE).all()


@pytest.mark.parametrize("kind", ["nan_calibration", "non_orthonormal", "bad_intrinsics"])
def test_scan_catches_what_build_catches(world: Path, tmp_path: Path, kind: str) -> None:
    def fn(rows: list[dict]) -> None:
        cs = next(r for r in rows if r.get("camera_intrinsic"))
        if kind == "nan_calibration":
            cs["translation"][0] = float("nan")
        elif kind == "non_orthonormal":
            cs["rotation"] = [0.5, 0.0, 0.0, 0.0]
        else:
            cs["camera_intrinsic"][2] = [0.0, 1.0, 1.0]

    edit_table(world, "calibrated_sensor", fn)
    needle = {"nan_calibration": "NaN", "non_orthonormal": "not orthonormal", "bad_intrinsics": "intrinsics"}[kind]
    one_error_line(*build(world, tmp_path / "s.zarr"), needle)
    one_error_line(*cli("scan", "--root", str(world)), needle)


# --- 13. fsspec URLs in every occdata command --------------------------------------------------------------
def test_file_urls_work_in_every_command(synth_root: Path, tmp_path: Path) -> None:
    store = tmp_path / "s.zarr"
    url = store.as_uri()  # file:///.../s.zarr
    assert url.startswith("file:///")
    root_url = synth_root.resolve().as_uri()
    code, out = cli("scan", "--root", root_url)
    assert code == 0, out
    code, out = cli("build", "--root", root_url, "--out", url, "--gts", (synth_root / "gts").resolve().as_uri(),
                    "--no-progress")
    assert code == 0, out
    assert store.is_dir()
    for args in (["info"], ["verify", "--no-progress"], ["bev-gt", "--no-progress"],
                 ["visibility", "--no-progress"],
                 ["dump", "-i", "0", "--out", (tmp_path / "d.npz").as_uri()],
                 ["check-projection", "-i", "0", "--out", str(tmp_path / "p.png")]):
        code, out = cli(args[0], "--store", url, *args[1:])
        assert code == 0, (args, out)
        assert "file:/" + str(store) not in out.replace(url, "")  # never the mangled form
    assert (tmp_path / "d.npz").is_file() and (tmp_path / "p.png").is_file()
    preds = tmp_path / "preds"
    preds.mkdir()
    reader = open_store(store)
    for i in range(reader.n_samples):
        sem = reader.sample_arrays(i, ("labels/semantics",))["labels/semantics"]
        np.savez(preds / f"{reader.token(i)}.npz", semantics=sem)
    code, out = cli("eval", "--store", url, "--pred", preds.as_uri(), "--no-rayiou", "--no-progress")
    assert code == 0, out
    code, out = cli("synth", "--out", (tmp_path / "tiny").as_uri(), "--scenes", "1", "--samples", "1",
                    "--width", "64", "--height", "36", "--no-progress")
    assert code == 0, out
    assert (tmp_path / "tiny" / "v1.0-mini" / "scene.json").is_file()
    one_error_line(*cli("info", "--store", "file:///nonexistent/x.zarr"), "/nonexistent/x.zarr")
    one_error_line(*cli("build", "--root", "s3://bucket/ns"), "--root", "local")


def test_non_file_fsspec_url_is_read(synth_store: Path) -> None:
    """A store behind another fsspec protocol (memory://, standing in for s3:// or gs://) is read by
    the store-reading commands as it is by the Python API."""
    import fsspec

    fs = fsspec.filesystem("memory")
    for f in synth_store.rglob("*"):
        if f.is_file():
            fs.pipe(f"/harden/s.zarr/{f.relative_to(synth_store).as_posix()}", f.read_bytes())
    try:
        code, out = cli("info", "--store", "memory://harden/s.zarr")
        assert code == 0, out
        assert "samples: 6 (done 6" in out
        code, out = cli("verify", "--store", "memory://harden/s.zarr", "--no-progress")
        assert code == 0, out
    finally:
        fs.rm("/harden", recursive=True)


def test_verify_images_finds_a_damaged_jpeg_that_checksums_cover(synth_store: Path, tmp_path: Path) -> None:
    """What an older build stored: a damaged JPEG whose checksum was taken over the damaged bytes.
    Plain verify cannot see it; `verify --images` names the sample and the camera."""
    import zarr

    from occdata.store.layout import checksummed_names

    store = tmp_path / "s.zarr"
    shutil.copytree(synth_store, store)
    g = zarr.open_group(str(store), mode="r+")
    i, cam = 2, 4
    start, length = (int(v) for v in g["images/offsets"][i, cam])
    good = g["images/jpeg"][start : start + length].tobytes()
    bad = _damage(good, "entropy_partly_zeroed")
    assert len(bad) == len(good)
    g["images/jpeg"][start : start + length] = np.frombuffer(bad, np.uint8)
    off = g["images/offsets"][i]
    blob = b"".join(g["images/jpeg"][int(s) : int(s) + int(n)].tobytes() for s, n in off)
    col = checksummed_names().index("images/jpeg")
    sums = g["status/checksum"][i]
    sums[col] = zlib.crc32(blob)
    g["status/checksum"][i] = sums
    code, out = cli("verify", "--store", str(store), "--no-progress")
    assert code == 0, out  # the checksum pass is blind to it
    code, out = cli("verify", "--store", str(store), "--no-progress", "--images")
    assert code == 1
    corrupt = [ln for ln in out.splitlines() if ln.startswith("CORRUPT")]
    assert len(corrupt) == 1 and corrupt[0].startswith(f"CORRUPT sample {i} ")
    assert "CAM_BACK" in corrupt[0] and "Corrupt JPEG data" in corrupt[0]
