"""Sanity checks for the official nuScenes scene split lists."""

from __future__ import annotations

import re

import pytest

from occdata.nuscenes.splits import MINI_TRAIN, MINI_VAL, TEST, TRAIN, VAL, official_split


def test_split_sizes() -> None:
    assert len(TRAIN) == 700
    assert len(VAL) == 150
    assert len(TEST) == 150
    assert len(MINI_TRAIN) == 8
    assert len(MINI_VAL) == 2


def test_full_splits_are_disjoint() -> None:
    assert not TRAIN & VAL
    assert not TRAIN & TEST
    assert not VAL & TEST
    assert len(TRAIN | VAL | TEST) == 1000


def test_scene_names_are_well_formed() -> None:
    pattern = re.compile(r"scene-\d{4}")
    for scene in TRAIN | VAL | TEST:
        assert pattern.fullmatch(scene), scene


def test_mini_splits() -> None:
    assert MINI_TRAIN == {
        "scene-0061",
        "scene-0553",
        "scene-0655",
        "scene-0757",
        "scene-0796",
        "scene-1077",
        "scene-1094",
        "scene-1100",
    }
    assert MINI_VAL == {"scene-0103", "scene-0916"}
    # The devkit's mini_train holds two scenes that the full release puts in val; mini_val is all val.
    assert MINI_TRAIN - TRAIN == {"scene-0553", "scene-0796"}
    assert MINI_TRAIN <= TRAIN | VAL
    assert MINI_VAL <= VAL


@pytest.mark.parametrize(
    ("scene", "version", "expected"),
    [
        ("scene-0061", "v1.0-mini", "mini_train"),
        ("scene-0916", "v1.0-mini", "mini_val"),
        ("scene-0001", "v1.0-mini", None),
        ("scene-0001", "v1.0-trainval", "train"),
        ("scene-0003", "v1.0-trainval", "val"),
        ("scene-0077", "v1.0-trainval", None),
        ("scene-0077", "v1.0-test", "test"),
        ("scene-0001", "v1.0-test", None),
        ("scene-0061", "my-custom-build", "train"),
        ("scene-0103", "my-custom-build", "val"),
        ("scene-1043", "my-custom-build", "test"),
        ("scene-9999", "my-custom-build", None),
        ("scene-9999", "v1.0-trainval", None),
    ],
)
def test_official_split(scene: str, version: str, expected: str | None) -> None:
    assert official_split(scene, version) == expected
