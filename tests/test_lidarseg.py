"""nuScenes-lidarseg reading and its Occ3D class mapping (occdata.nuscenes.lidarseg).

Independent truth: the official devkit (its class mapper, its colormap's class order, and its own
loading of a lidarseg tree, run in the devkit venv via OCCDATA_DEVKIT_PYTHON), the real scene-0916
category.json (its `index` values), and hand-made files. Real tables are copied only to temp folders.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from occdata.constants import CLASS_NAMES
from occdata.errors import OccDataError
from occdata.nuscenes import (
    DROP,
    LIDARSEG_NAMES,
    OCC3D_FROM_LIDARSEG,
    lidarseg_index_names,
    load_lidar_points,
    load_lidarseg_index,
    load_nuscenes,
    occ3d_lut,
    read_lidarseg,
)

needs_devkit = pytest.mark.skipif(
    not os.environ.get("OCCDATA_DEVKIT_PYTHON"),
    reason="set OCCDATA_DEVKIT_PYTHON to a python with nuscenes-devkit (scripts/devkit_env.sh)",
)

DEVKIT_MAPPER = r'''
import json, sys
from types import SimpleNamespace
from nuscenes.eval.lidarseg.utils import LidarsegClassMapper
from nuscenes.utils.color_map import get_colormap
names = json.loads(sys.argv[1])
mapper = LidarsegClassMapper(SimpleNamespace(lidarseg_name2idx_mapping={n: i for i, n in enumerate(names)}))
print(json.dumps({"coarse": {n: mapper.fine_idx_2_coarse_idx_mapping[i] for i, n in enumerate(names)},
                  "coarse_names": mapper.coarse_name_2_coarse_idx_mapping,
                  "ignore": mapper.ignore_class["index"], "colormap_order": list(get_colormap())}))
'''

DEVKIT_TREE = r'''
import json, os, sys
import numpy as np
from nuscenes import NuScenes
from nuscenes.eval.lidarseg.utils import LidarsegClassMapper
nusc = NuScenes(version="v1.0-mini", dataroot=sys.argv[1], verbose=False)
mapper = LidarsegClassMapper(nusc)
out = {"idx2name": {str(k): v for k, v in nusc.lidarseg_idx2name_mapping.items()}, "coarse": {}}
for rec in nusc.lidarseg:
    labels = np.fromfile(os.path.join(nusc.dataroot, rec["filename"]), dtype=np.uint8)
    out["coarse"][rec["sample_data_token"]] = mapper.convert_label(labels).tolist()
json.dump(out, open(sys.argv[2], "w"))
'''


def _devkit(script: str, *args: str) -> str:
    res = subprocess.run([os.environ["OCCDATA_DEVKIT_PYTHON"], "-c", script, *args],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


# --- the class mapping ------------------------------------------------------------------------------
def test_mapping_shape_and_documented_choices() -> None:
    assert len(LIDARSEG_NAMES) == 32 == len(set(LIDARSEG_NAMES)) and tuple(OCC3D_FROM_LIDARSEG) == LIDARSEG_NAMES
    assert {n for n, c in OCC3D_FROM_LIDARSEG.items() if c == DROP} == {"noise", "vehicle.ego"}
    # Every Occ3D class 1..16 is reached; 0 `others` for the occupied ignore classes.
    assert set(OCC3D_FROM_LIDARSEG.values()) == {*range(17), DROP}
    assert OCC3D_FROM_LIDARSEG["vehicle.car"] == CLASS_NAMES.index("car") == 4
    assert OCC3D_FROM_LIDARSEG["static.vegetation"] == CLASS_NAMES.index("vegetation") == 16
    assert OCC3D_FROM_LIDARSEG["static.other"] == OCC3D_FROM_LIDARSEG["animal"] == 0


def test_names_match_the_real_category_indices(real_seq_root: Path) -> None:
    """The real scene-0916 category.json carries lidarseg `index` values for 14 of the classes."""
    names = lidarseg_index_names(real_seq_root, "v1.0-mini")
    assert len(names) == 14
    for index, name in names.items():
        assert LIDARSEG_NAMES[index] == name


@needs_devkit
def test_mapping_matches_devkit_class_mapper() -> None:
    dk = json.loads(_devkit(DEVKIT_MAPPER, json.dumps(list(LIDARSEG_NAMES))))
    assert dk["colormap_order"] == list(LIDARSEG_NAMES)  # the devkit's class list, in index order
    assert dk["ignore"] == 0
    for name, coarse in dk["coarse_names"].items():  # the challenge's 16 classes are Occ3D's 1..16
        assert coarse == 0 or CLASS_NAMES[coarse] == name
    for name, ours in OCC3D_FROM_LIDARSEG.items():
        if 1 <= ours <= 16:
            assert dk["coarse"][name] == ours, name
        else:
            assert ours in (0, DROP) and dk["coarse"][name] == 0, name


def test_lut() -> None:
    lut = occ3d_lut(dict(enumerate(LIDARSEG_NAMES)))
    assert lut.shape == (256,) and lut.dtype == np.uint8
    assert lut[:32].tolist() == [OCC3D_FROM_LIDARSEG[n] for n in LIDARSEG_NAMES]
    assert (lut[32:] == DROP).all()
    # Indices follow category.json, not LIDARSEG_NAMES: a reordered table maps by name.
    assert occ3d_lut({7: "vehicle.car", 40: "flat.sidewalk"})[[7, 40, 0]].tolist() == [4, 13, DROP]
    with pytest.raises(OccDataError, match="'vehicle.spaceship' .* is not a nuScenes-lidarseg class"):
        occ3d_lut({3: "vehicle.spaceship"})


# --- files --------------------------------------------------------------------------------------------
def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rows))


def test_index_and_labels_on_a_hand_made_tree(tmp_path: Path) -> None:
    root = tmp_path / "nusc"
    assert load_lidarseg_index(root, "v1.0-x") == {}  # no lidarseg.json: no lidarseg
    _write(root / "v1.0-x" / "lidarseg.json", [
        {"token": "l1", "sample_data_token": "sd1", "filename": "lidarseg/v1.0-x/sd1_lidarseg.bin"},
        {"token": "l2", "sample_data_token": "sd2", "filename": "lidarseg/v1.0-x/sd2_lidarseg.bin"},
    ])
    index = load_lidarseg_index(root, "v1.0-x")
    assert index == {"sd1": root / "lidarseg/v1.0-x/sd1_lidarseg.bin", "sd2": root / "lidarseg/v1.0-x/sd2_lidarseg.bin"}
    index["sd1"].parent.mkdir(parents=True)
    index["sd1"].write_bytes(bytes([0, 17, 31, 24]))
    labels = read_lidarseg(index["sd1"], 4)
    assert labels.dtype == np.uint8 and labels.tolist() == [0, 17, 31, 24]
    assert occ3d_lut(dict(enumerate(LIDARSEG_NAMES)))[labels].tolist() == [DROP, 4, DROP, 11]
    with pytest.raises(OccDataError, match="holds 4 labels, its point cloud has 5 points") as info:
        read_lidarseg(index["sd1"], 5)
    assert str(index["sd1"]) in str(info.value)
    with pytest.raises(OccDataError, match="missing lidarseg file: .*sd2_lidarseg.bin"):
        read_lidarseg(index["sd2"], 4)


@pytest.mark.parametrize("rows, message", [
    ([{"token": "l1", "sample_data_token": "sd1", "filename": "../outside.bin"}], "points outside"),
    ([{"token": "l1", "sample_data_token": "sd1", "filename": 7}], "is not a non-empty string"),
    ([{"token": "l1", "filename": "lidarseg/a.bin"}], "no string sample_data_token"),
    ([{"token": "l1", "sample_data_token": "sd1", "filename": "lidarseg/a.bin"},
      {"token": "l2", "sample_data_token": "sd1", "filename": "lidarseg/b.bin"}], "has two lidarseg rows"),
])
def test_bad_lidarseg_json(tmp_path: Path, rows: list[dict], message: str) -> None:
    _write(tmp_path / "v1.0-x" / "lidarseg.json", rows)
    with pytest.raises(OccDataError, match=message) as info:
        load_lidarseg_index(tmp_path, "v1.0-x")
    assert "\n" not in str(info.value) and "lidarseg.json" in str(info.value)


@pytest.mark.parametrize("rows, message", [
    ([{"token": "c1", "name": "vehicle.car", "index": "17"}], "index '17' is not an integer 0..255"),
    ([{"token": "c1", "name": "vehicle.car", "index": 300}], "is not an integer 0..255"),
    ([{"token": "c1", "name": "vehicle.car", "index": 17},
      {"token": "c2", "name": "vehicle.truck", "index": 17}], "index 17 is also category 'vehicle.car'"),
])
def test_bad_category_index(tmp_path: Path, rows: list[dict], message: str) -> None:
    _write(tmp_path / "v1.0-x" / "category.json", rows)
    with pytest.raises(OccDataError, match=message) as info:
        lidarseg_index_names(tmp_path, "v1.0-x")
    assert "\n" not in str(info.value) and "'c" in str(info.value)


# --- a lidarseg tree read by the devkit and by us ------------------------------------------------------
def _lidarseg_tree(real_seq: Path, tmp_path: Path, n_keyframes: int) -> tuple[Path, list[str]]:
    """Real scene-0916 tables (copied) and keyframe files (symlinked), category.json extended to the
    32 lidarseg classes (the real rows keep their tokens), made-up labels for `n_keyframes` LiDARs."""
    root = tmp_path / "nusc"
    shutil.copytree(real_seq / "v1.0-mini", root / "v1.0-mini")
    for folder in ("samples", "maps"):
        (root / folder).symlink_to((real_seq / folder).resolve(), target_is_directory=True)
    cat_path = root / "v1.0-mini" / "category.json"
    cats = json.loads(cat_path.read_text())
    have = {c["name"] for c in cats}
    cats += [{"token": f"{i:032x}", "name": n, "description": "", "index": i}
             for i, n in enumerate(LIDARSEG_NAMES) if n not in have]
    cat_path.write_text(json.dumps(cats))
    ds = load_nuscenes(root, check_files=True)
    rows, tokens = [], []
    for k, sample in enumerate(ds.samples[:n_keyframes]):
        n_points = len(load_lidar_points(sample.lidar.path))
        rel = f"lidarseg/v1.0-mini/{sample.lidar.token}_lidarseg.bin"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(((np.arange(n_points) * 7 + k) % 32).astype(np.uint8).tobytes())
        rows.append({"token": f"{k:032x}", "sample_data_token": sample.lidar.token, "filename": rel})
        tokens.append(sample.lidar.token)
    (root / "v1.0-mini" / "lidarseg.json").write_text(json.dumps(rows))
    return root, tokens


@needs_devkit
def test_lidarseg_tree_matches_devkit(real_seq_root: Path, tmp_path: Path) -> None:
    root, tokens = _lidarseg_tree(real_seq_root, tmp_path, n_keyframes=3)
    _devkit(DEVKIT_TREE, str(root), str(tmp_path / "dk.json"))
    dk = json.loads((tmp_path / "dk.json").read_text())
    names = lidarseg_index_names(root, "v1.0-mini")
    assert names == {int(k): v for k, v in dk["idx2name"].items()} and len(names) == 32
    lut = occ3d_lut(names)
    index = load_lidarseg_index(root, "v1.0-mini")
    ds = load_nuscenes(root)
    assert sorted(index) == sorted(tokens) == sorted(dk["coarse"])
    for sample in ds.samples[:3]:
        n_points = len(load_lidar_points(sample.lidar.path))
        ours = lut[read_lidarseg(index[sample.lidar.token], n_points)]
        theirs = np.asarray(dk["coarse"][sample.lidar.token])
        named = (ours >= 1) & (ours <= 16)
        assert (ours[named] == theirs[named]).all()
        assert (theirs[~named] == 0).all() and set(np.unique(ours[~named]).tolist()) == {0, DROP}
