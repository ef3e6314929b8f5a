"""occdata.formats.occ3d: the one reader/writer of Occ3D label files, against the real label and bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from occdata.errors import OccDataError
from occdata.formats.occ3d import label_path, list_label_files, read_label, read_prediction, write_label


def test_real_occ3d_label_reads_with_its_masks(real_occ3d_label: Path) -> None:
    label = read_label(real_occ3d_label, require_masks=True)
    with np.load(real_occ3d_label, allow_pickle=False) as z:  # the file as Occ3D ships it
        for k in ("semantics", "mask_lidar", "mask_camera"):
            np.testing.assert_array_equal(label[k], z[k])
    assert label["semantics"].dtype == np.uint8 and label["semantics"].shape == (200, 200, 16)
    assert 0 < label["mask_camera"].sum() < label["mask_lidar"].size


def test_write_read_round_trip_same_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    arrays = {"semantics": rng.integers(0, 18, (200, 200, 16), dtype=np.uint8),
              "mask_lidar": rng.integers(0, 2, (200, 200, 16), dtype=np.uint8),
              "mask_camera": rng.integers(0, 2, (200, 200, 16), dtype=np.uint8)}
    a, b = label_path(tmp_path / "a", "scene-1", "tok"), label_path(tmp_path / "b", "scene-1", "tok")
    write_label(a, arrays)
    write_label(b, arrays)
    assert a.read_bytes() == b.read_bytes()  # no zip timestamps
    back = read_label(a)
    for k, v in arrays.items():
        np.testing.assert_array_equal(back[k], v)
    assert list_label_files(tmp_path / "a") == [a]
    np.testing.assert_array_equal(read_prediction(a), arrays["semantics"])


def test_missing_masks_are_zeros_unless_required(tmp_path: Path) -> None:
    p = tmp_path / "l.npz"
    write_label(p, {"semantics": np.full((200, 200, 16), 17, np.uint8)})
    assert read_label(p)["mask_camera"].sum() == 0
    with pytest.raises(OccDataError, match=r"missing keys \['mask_lidar', 'mask_camera'\]"):
        read_label(p, require_masks=True)


@pytest.mark.parametrize("bad, needle", [
    ("folder", "a folder"), ("absent", "file not found"), ("garbage", "not a readable .npz"),
    ("shape", "has shape (200, 200, 8)"), ("dtype", "dtype float32"), ("range", "values outside 0..17"),
    ("mask", "mask_lidar has 1 values outside 0..1"), ("pickle", "not a readable .npz"),
])
def test_bad_label_files_give_one_line_naming_the_file(tmp_path: Path, bad: str, needle: str) -> None:
    p = tmp_path / "labels.npz"
    sem = np.zeros((200, 200, 16), np.uint8)
    if bad == "folder":
        p.mkdir()
    elif bad == "garbage":
        p.write_bytes(b"PK\x03\x04 not really")
    elif bad == "shape":
        np.savez(p, semantics=sem[:, :, :8])
    elif bad == "dtype":
        np.savez(p, semantics=sem.astype(np.float32))
    elif bad == "range":
        sem[0, 0, 0] = 18
        np.savez(p, semantics=sem)
    elif bad == "mask":
        m = np.zeros_like(sem)
        m[1, 2, 3] = 2
        np.savez(p, semantics=sem, mask_lidar=m)
    elif bad == "pickle":
        np.savez(p, semantics=np.array([{"a": 1}], dtype=object))
    with pytest.raises(OccDataError) as err:
        read_label(p)
    msg = str(err.value)
    assert needle in msg and str(p) in msg and "\n" not in msg
