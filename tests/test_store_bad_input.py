"""Bad samples: a per-sample error naming the file and reason; skip records it, fail stops.

Also: `occdata verify` finds a flipped byte in any chunk and names the sample.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner
from replicated_tree import make_replicated_tree

from cli.occdata_cli import main
from occdata.store.layout import STATE_DONE, STATE_ERROR
from occdata.store.reader import open_store

BAD_INDEX = 4  # the sample that gets broken (scene 0, 5th sample)


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


@pytest.fixture
def tree(real_nuscenes_root, real_occ3d_label, tmp_path) -> Path:
    return make_replicated_tree(real_nuscenes_root, real_occ3d_label, tmp_path / "ns", 2, 4)


def _sample_data_row(tree: Path, channel_dir: str) -> tuple[list[dict], dict]:
    rows = json.loads((tree / "v1.0-mini" / "sample_data.json").read_text())
    samples = json.loads((tree / "v1.0-mini" / "sample.json").read_text())
    token = samples[BAD_INDEX]["token"]
    row = next(r for r in rows if r["sample_token"] == token and f"/{channel_dir}/" in r["filename"])
    return rows, row


def _repoint(tree: Path, channel_dir: str, data: bytes, name: str) -> Path:
    rows, row = _sample_data_row(tree, channel_dir)
    row["filename"] = f"samples/{channel_dir}/{name}"
    (tree / "v1.0-mini" / "sample_data.json").write_text(json.dumps(rows))
    path = tree / row["filename"]
    path.write_bytes(data)
    return path


def _label_path(tree: Path) -> Path:
    samples = json.loads((tree / "v1.0-mini" / "sample.json").read_text())
    return next((tree / "gts").glob(f"*/{samples[BAD_INDEX]['token']}/labels.npz"))


def _break(kind: str, tree: Path, real_label: Path) -> str:
    """Break sample BAD_INDEX; return a string the error must contain."""
    jpg = next((tree / "samples" / "CAM_BACK").iterdir()).resolve().read_bytes()
    lidar = next((tree / "samples" / "LIDAR_TOP").iterdir()).resolve().read_bytes()
    if kind == "corrupt_jpeg":
        _repoint(tree, "CAM_BACK", jpg[: len(jpg) // 2], "bad.jpg")
        return "corrupt JPEG"
    if kind == "not_a_jpeg":
        _repoint(tree, "CAM_BACK", b"GIF89a" + jpg[6:], "bad.jpg")
        return "bad.jpg"
    if kind == "truncated_lidar":
        _repoint(tree, "LIDAR_TOP", lidar[:1000] + lidar[1000:1007], "short.pcd.bin")
        return "not a positive multiple of 20"
    if kind == "missing_file":
        rows, row = _sample_data_row(tree, "CAM_FRONT")
        row["filename"] = "samples/CAM_FRONT/gone.jpg"
        (tree / "v1.0-mini" / "sample_data.json").write_text(json.dumps(rows))
        return "gone.jpg"
    if kind in ("label_keys", "label_shape", "label_values"):
        with np.load(real_label) as npz:
            d = {k: npz[k] for k in npz.files}
        if kind == "label_keys":
            d["sem"] = d.pop("semantics")
        elif kind == "label_shape":
            d["mask_camera"] = d["mask_camera"][:, :, :8]
        else:
            d["semantics"] = d["semantics"].copy()
            d["semantics"][0, 0, 0] = 40
        path = _label_path(tree)
        path.unlink()
        np.savez_compressed(path, **d)
        return "labels.npz"
    if kind in ("nan_calibration", "non_orthonormal"):
        cs_rows = json.loads((tree / "v1.0-mini" / "calibrated_sensor.json").read_text())
        rows, row = _sample_data_row(tree, "CAM_FRONT")
        bad = dict(next(c for c in cs_rows if c["token"] == row["calibrated_sensor_token"]))
        bad["token"] = "b" * 32
        if kind == "nan_calibration":
            bad["translation"] = [float("nan"), 0.0, 1.5]
        else:
            bad["rotation"] = [2.0, 0.1, 0.0, 0.0]
        cs_rows.append(bad)
        row["calibrated_sensor_token"] = bad["token"]
        (tree / "v1.0-mini" / "calibrated_sensor.json").write_text(json.dumps(cs_rows))
        (tree / "v1.0-mini" / "sample_data.json").write_text(json.dumps(rows))
        return "NaN" if kind == "nan_calibration" else "orthonormal"
    raise AssertionError(kind)


KINDS = ["corrupt_jpeg", "not_a_jpeg", "truncated_lidar", "missing_file", "label_keys", "label_shape",
         "label_values", "nan_calibration", "non_orthonormal"]


@pytest.mark.parametrize("kind", KINDS)
def test_skip_records_error_and_keeps_going(kind: str, tree, real_occ3d_label, tmp_path) -> None:
    needle = _break(kind, tree, real_occ3d_label)
    out = tmp_path / "s.zarr"
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(out),
                      "--on-error", "skip", "--block-samples", "3", "--no-progress")
    assert code == 0, text
    reader = open_store(out)
    state = reader.state
    assert state[BAD_INDEX] == STATE_ERROR
    assert (np.delete(state, BAD_INDEX) == STATE_DONE).all()
    (err,) = reader.attrs["errors"]
    assert err["index"] == BAD_INDEX and needle in err["reason"]
    code, text = _cli("info", "--store", str(out))
    assert f"sample {BAD_INDEX}" in text and needle in text
    code, text = _cli("verify", "--store", str(out), "--no-progress")
    assert code == 0, text


@pytest.mark.parametrize("kind", ["corrupt_jpeg", "label_shape"])
def test_fail_stops_with_one_line_and_keeps_earlier_samples(kind: str, tree, real_occ3d_label, tmp_path) -> None:
    needle = _break(kind, tree, real_occ3d_label)
    out = tmp_path / "f.zarr"
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(out),
                      "--block-samples", "3", "--no-progress")
    assert code != 0 and "Traceback" not in text
    lines = [ln for ln in text.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1 and needle in lines[0] and f"sample {BAD_INDEX}" in lines[0]
    state = open_store(out).state
    assert (state[:BAD_INDEX] == STATE_DONE).all() and (state[BAD_INDEX:] == 0).all()
    # Fix the input, resume: everything completes.
    shutil.rmtree(tree)
    make_replicated_tree(*_real(real_occ3d_label), tree, 2, 4)
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(out),
                      "--block-samples", "3", "--resume", "--no-progress")
    assert code == 0, text
    assert (open_store(out).state == STATE_DONE).all()


def _real(real_label: Path) -> tuple[Path, Path]:
    from conftest import REAL_NUSCENES

    return REAL_NUSCENES, real_label


@pytest.fixture
def good_store(tree, tmp_path) -> Path:
    out = tmp_path / "g.zarr"
    code, text = _cli("build", "--root", str(tree), "--gts", str(tree / "gts"), "--out", str(out),
                      "--block-samples", "3", "--no-progress")
    assert code == 0, text
    return out


def _flip(path: Path, frac: float) -> None:
    data = bytearray(path.read_bytes())
    data[int(len(data) * frac)] ^= 0x40
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("chunk", "frac", "expect_index", "array"),
    [
        # an early byte of the 3rd MiB of JPEG data (blocks start on chunk boundaries: a chunk's
        # start is always data, its tail may be the zero padding before the next block)
        ("images/jpeg/c/2", 0.01, None, "images/jpeg"),
        ("labels/semantics/c/1/0/0/0", 0.6, None, "labels/semantics"),  # shard of samples 3..5
        ("calib/K/c/1/0/0/0", 0.5, None, "calib/K"),
        ("depth/uvd/c/0/0", 0.3, None, "depth/uvd"),
    ],
)
def test_verify_reports_flipped_byte(good_store, chunk: str, frac: float, expect_index, array: str) -> None:
    path = good_store / chunk
    assert path.is_file(), sorted(p.relative_to(good_store).as_posix() for p in good_store.rglob("c/*"))[:20]
    _flip(path, frac)
    code, text = _cli("verify", "--store", str(good_store), "--no-progress")
    assert code != 0
    bad = [ln for ln in text.splitlines() if ln.startswith("CORRUPT sample")]
    assert bad and all(array in ln for ln in bad), text
    if array == "labels/semantics" or array == "calib/K":
        assert all(int(ln.split()[2]) in (3, 4, 5) for ln in bad), text


def test_reader_names_sample_on_corrupt_chunk(good_store) -> None:
    from occdata.errors import OccDataError

    shard = good_store / "labels/semantics/c/1/0/0/0"
    shard.write_bytes(shard.read_bytes()[:100])
    reader = open_store(good_store)
    with pytest.raises(OccDataError, match="sample 4"):
        reader.sample_arrays(4, ("labels/semantics",))
    assert zarr.open_group(str(good_store), mode="r")["labels/semantics"][0].shape == (200, 200, 16)
