"""Label grids as values: each benchmark's preset written and read back the way its own loader reads
it (the loaders' steps are written out here from docs/labels.md, not imported from occdata), and the
same scene on several grids from one aggregation agrees where the grids overlap."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.constants import CLASS_NAMES, FREE_LABEL, GRID
from occdata.errors import OccDataError
from occdata.formats.gridfiles import LabelSite, grid_label_path, read_grid_label, write_grid_label
from occdata.formats.gridspec import GRID_PRESETS, custom_grid, grids_from_options
from occdata.geometry import invert_rigid, transform_points

SITE = LabelSite("scene-0001", "sc0tok", "smp0tok", "lid0tok", "n008__LIDAR_TOP__1537297541450317.pcd.bin")
CAR, OTHERS, ROAD = CLASS_NAMES.index("car"), CLASS_NAMES.index("others"), CLASS_NAMES.index("driveable_surface")


def _semantics(shape: tuple[int, int, int]) -> np.ndarray:
    sem = np.full(shape, FREE_LABEL, np.uint8)
    sem[3, 5, 7] = CAR
    sem[0, 0, 0] = OTHERS
    sem[shape[0] - 1, 2, 1] = ROAD
    return sem


def _surroundocc_loader(path: Path, shape: tuple[int, int, int]) -> np.ndarray:
    """SurroundOcc: (N, 4) [x, y, z, class]; class 0 -> 255 (ignore); dense zeros, voxel[x, y, z] = class."""
    occ = np.load(path).astype(np.float32)
    occ[occ[:, 3] == 0, 3] = 255
    dense = np.zeros(shape, np.float32)
    idx = occ[:, :3].astype(np.int64)
    dense[idx[:, 0], idx[:, 1], idx[:, 2]] = occ[:, 3]
    return dense


def _openoccupancy_loader(path: Path, shape: tuple[int, int, int]) -> np.ndarray:
    """OpenOccupancy: (N, 4) [z, y, x, class]; class 0 (noise) -> 255; dense zeros, voxel[x, y, z]."""
    pcd = np.load(path)
    label = pcd[:, 3].copy()
    label[label == 0] = 255
    dense = np.zeros(shape, np.int64)
    dense[pcd[:, 2], pcd[:, 1], pcd[:, 0]] = label
    return dense


def test_occ3d_file_is_the_occ3d_layout(tmp_path: Path) -> None:
    spec = GRID_PRESETS["occ3d"]
    sem = _semantics(spec.shape)
    masks = {"mask_lidar": np.ones(spec.shape, np.uint8), "mask_camera": (sem != FREE_LABEL).astype(np.uint8)}
    path = write_grid_label(spec, tmp_path, SITE, {"semantics": sem, **masks})
    assert path == tmp_path / "scene-0001" / "smp0tok" / "labels.npz"
    with np.load(path) as f:  # the Occ3D loader: three keys, uint8 (200, 200, 16), 17 = free
        assert f.files == ["semantics", "mask_lidar", "mask_camera"]
        np.testing.assert_array_equal(f["semantics"], sem)
        assert f["semantics"].dtype == np.uint8 and f["mask_camera"].sum() == 3


def test_openocc_v2_has_its_class_order_flow_and_no_others(tmp_path: Path) -> None:
    spec = GRID_PRESETS["openocc-v2"]
    sem = _semantics(spec.shape)
    flow = np.zeros((*spec.shape, 2), np.float32)
    flow[3, 5, 7] = (4.5, -0.5)
    path = write_grid_label(spec, tmp_path, SITE, {"semantics": sem, "flow": flow})
    assert path == tmp_path / "scene-0001" / "smp0tok" / "labels.npz"
    f = np.load(path)  # OpenOcc v2's loader reads these two keys
    semantics, got_flow = f["semantics"], f["flow"]
    assert semantics.shape == (200, 200, 16) and got_flow.shape == (200, 200, 16, 2)
    assert semantics[3, 5, 7] == 0  # car is its class 0
    assert semantics[199, 2, 1] == 10  # driveable_surface is its 10
    assert semantics[0, 0, 0] == 16 and (semantics == 16).sum() == semantics.size - 2  # "others" -> free 16
    np.testing.assert_array_equal(got_flow, flow)


@pytest.mark.parametrize("name", ["occ3d", "openocc-v2", "occ3d-0.8m"])
def test_npz_layouts_are_written_by_the_one_occ3d_writer(name: str, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Every grid with a labels.npz layout goes through `occ3d.write_label` at `occ3d.label_path`: the file
    bytes and place have one definition, whatever the grid."""
    from occdata.formats import gridfiles, occ3d

    spec = custom_grid(0.8, GRID.lower, GRID.upper) if name.endswith("m") else GRID_PRESETS[name]
    written: list[tuple[Path, list[str]]] = []
    monkeypatch.setattr(gridfiles, "write_label", lambda path, arrays: written.append((Path(path), list(arrays))))
    path = write_grid_label(spec, tmp_path, SITE, {"semantics": _semantics(spec.shape),
                                                   "mask_lidar": np.ones(spec.shape, np.uint8)})
    want = ["semantics", "mask_lidar", *(["flow"] if name == "openocc-v2" else [])]
    assert path == occ3d.label_path(tmp_path, SITE.scene_name, SITE.sample_token) and written == [(path, want)]
    assert not path.exists()  # nothing else wrote it
    monkeypatch.undo()
    assert gridfiles.write_label is occ3d.write_label


@pytest.mark.parametrize("name", ["surroundocc", "openoccupancy"])
def test_sparse_layouts_read_back_as_their_loaders_read_them(tmp_path: Path, name: str) -> None:
    spec = GRID_PRESETS[name]
    sem = _semantics(spec.shape)
    path = write_grid_label(spec, tmp_path, SITE, {"semantics": sem})
    want = {"surroundocc": tmp_path / "samples" / "n008__LIDAR_TOP__1537297541450317.pcd.bin.npy",
            "openoccupancy": tmp_path / "scene_sc0tok" / "occupancy" / "lid0tok.npy"}[name]
    assert path == want == grid_label_path(spec, tmp_path, SITE)
    rows = np.load(path)
    assert rows.shape == (3, 4) and rows.dtype == np.int64  # the occupied voxels only
    loader = _surroundocc_loader if name == "surroundocc" else _openoccupancy_loader
    dense = loader(path, spec.shape)
    assert dense[3, 5, 7] == 4  # car: lidarseg-16 id 4
    assert dense[spec.shape[0] - 1, 2, 1] == 11  # driveable_surface: 11
    assert dense[0, 0, 0] == 255  # our "others" is their noise: ignored
    assert (dense != 0).sum() == 3  # every other voxel empty
    np.testing.assert_array_equal(read_grid_label(spec, path)["semantics"], dense.astype(np.uint8))


def test_bad_grid_files_and_grids_are_one_line(tmp_path: Path) -> None:
    spec = GRID_PRESETS["surroundocc"]
    bad = tmp_path / "bad.npy"
    np.save(bad, np.array([[500, 0, 0, 4]]))
    with pytest.raises(OccDataError, match="outside"):
        read_grid_label(spec, bad)
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    with pytest.raises(OccDataError, match="bad surroundocc label"):
        read_grid_label(spec, tmp_path / "junk.npy")
    with pytest.raises(OccDataError, match="whole number"):
        grids_from_options((), 0.3, (-40, -40, -1, 40, 40, 5.4))  # 6.4 m is not whole 0.3 m voxels
    with pytest.raises(OccDataError, match="unknown grid"):
        grids_from_options(("occ4d",))
    assert [g.name for g in grids_from_options()] == ["occ3d"]
    assert [g.name for g in grids_from_options(("surroundocc", "occ3d"), 0.2)] == ["surroundocc", "occ3d",
                                                                                   "occ3d-0.2m"]
    with pytest.raises(OccDataError, match="shape"):
        write_grid_label(GRID_PRESETS["occ3d"], tmp_path, SITE, {"semantics": np.zeros((2, 2, 2), np.uint8)})


# -- one aggregation, several grids ---------------------------------------------------------------
@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from occdata.synth import SynthConfig, synthesize

    return synthesize(SynthConfig(out=tmp_path_factory.mktemp("grids") / "world", progress=False, scenes=1,
                                  samples=3, seed=5, width=320, height=180))


@pytest.fixture(scope="module")
def labelled(world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("grids-out") / "labels"
    res = CliRunner().invoke(main, ["labels", "--root", str(world), "--out", str(out), "--grid", "occ3d", "--grid",
                                    "surroundocc", "--grid", "openocc-v2", "--voxel-size", "0.2", "--no-progress"])
    assert res.exit_code == 0, res.output
    return out


def _samples(world: Path) -> list:
    from occdata.nuscenes import find_version, load_nuscenes

    return list(load_nuscenes(world, find_version(world, None)).samples)


def test_labels_writes_every_grid_and_says_so(world: Path, labelled: Path) -> None:
    manifest = json.loads((labelled / "labels.json").read_text())
    assert [g["name"] for g in manifest["grids"]] == ["occ3d", "surroundocc", "openocc-v2", "occ3d-0.2m"]
    assert [g["folder"] for g in manifest["grids"]] == [".", "surroundocc", "openocc-v2", "occ3d-0.2m"]
    assert manifest["grids"][1]["frame"] == "lidar" and manifest["grids"][1]["classes"]["noise"] == 0
    moving = 0
    for s in _samples(world):
        assert (labelled / s.scene_name / s.token / "labels.npz").is_file()
        assert (labelled / "surroundocc" / "samples" / f"{s.lidar.path.name}.npy").is_file()
        f = np.load(labelled / "openocc-v2" / s.scene_name / s.token / "labels.npz")
        speed = np.linalg.norm(f["flow"], axis=-1)
        assert not speed[f["semantics"] >= 10].any()  # ground, buildings, vegetation, free: no flow
        moving += int((speed > 0.5).sum())
    assert moving > 50  # the world's driving actors carry their box velocity
    res = CliRunner().invoke(main, ["labels", "--root", str(world), "--out", str(labelled), "--resume",
                                    "--no-progress"])  # other grids than the run being resumed
    assert res.exit_code != 0 and "other settings" in res.output


def test_two_voxel_sizes_agree_where_the_grids_overlap(world: Path, labelled: Path) -> None:
    """A 0.4 m voxel is occupied exactly when one of its eight 0.2 m children is (the same points, the
    same frame): the occupancy of the fine grid pooled 2x2x2 equals the coarse grid's, everywhere."""
    for s in _samples(world):
        coarse = read_grid_label(GRID_PRESETS["occ3d"], labelled / s.scene_name / s.token / "labels.npz")
        fine = read_grid_label(custom_grid(0.2, (-40, -40, -1), (40, 40, 5.4)),
                               labelled / "occ3d-0.2m" / s.scene_name / s.token / "labels.npz")
        pooled = (fine["semantics"] != FREE_LABEL).reshape(200, 2, 200, 2, 16, 2).any(axis=(1, 3, 5))
        np.testing.assert_array_equal(pooled, coarse["semantics"] != FREE_LABEL)
        assert pooled.sum() > 1000


def _dilated(mask: np.ndarray) -> np.ndarray:
    """`mask` grown by one voxel along every axis and diagonal (3 x 3 x 3)."""
    out = mask.copy()
    padded = np.pad(mask, 1)
    X, Y, Z = mask.shape
    for dx in range(3):
        for dy in range(3):
            for dz in range(3):
                out |= padded[dx:dx + X, dy:dy + Y, dz:dz + Z]
    return out


def test_the_lidar_frame_grid_holds_the_same_surfaces_in_the_global_frame(world: Path, labelled: Path) -> None:
    """Every occupied SurroundOcc voxel (0.5 m, LiDAR frame), its centre mapped to the global frame by the
    keyframe's LiDAR pose and back into key ego, lands next to (within one 0.4 m voxel of) an occupied
    Occ3D voxel of the same class (lidarseg-16 ids = ours)."""
    occ_spec, sur_spec = GRID_PRESETS["occ3d"], GRID_PRESETS["surroundocc"]
    for s in _samples(world):
        occ = read_grid_label(occ_spec, labelled / s.scene_name / s.token / "labels.npz")["semantics"]
        sur = read_grid_label(sur_spec, labelled / "surroundocc" / "samples" / f"{s.lidar.path.name}.npy")
        sur = sur["semantics"]
        idx = np.argwhere((sur > 0) & (sur < 255))
        p_global = transform_points(s.T_global_from_keyego @ s.lidar.T_ego_from_lidar,
                                    (idx + 0.5) * 0.5 + np.array(sur_spec.grid.lower))
        p_key = transform_points(invert_rigid(s.T_global_from_keyego), p_global)
        o_idx = occ_spec.grid.index_of(p_key)
        inside = ((o_idx >= 0) & (o_idx < np.array(occ_spec.shape))).all(1)
        assert inside.sum() > 500
        cls = sur[tuple(idx[inside].T)]
        near = np.zeros(len(cls), bool)
        for c in np.unique(cls):
            grown = _dilated(occ == c)
            pick = cls == c
            near[pick] = grown[tuple(o_idx[inside][pick].T)]
        assert near.mean() >= 0.97, near.mean()


def test_train_on_a_store_of_another_grid_stops_at_start_in_one_line(synth_store: Path, tmp_path: Path) -> None:
    import shutil

    import zarr

    from cli.fastocc_cli import main as fastocc_main

    store = tmp_path / "other_grid.zarr"
    shutil.copytree(synth_store, store)
    group = zarr.open_group(str(store), mode="r+")
    group.attrs["grid"] = {**group.attrs["grid"], "voxel_size": 0.2, "shape": [400, 400, 32]}
    res = CliRunner().invoke(fastocc_main, ["train", "--store", str(store), "--out", str(tmp_path / "run"),
                                            "--epochs", "1", "--no-progress"])
    assert res.exit_code == 1, res.output
    # An edited attribute that names no grid is refused when the store is opened (real stores of other
    # grids: tests/test_store_grids.py::test_fastocc_stops_at_start_on_a_store_of_another_grid).
    assert "store grid attribute" in res.output and "not Occ3D's grid" in res.output
    assert "Traceback" not in res.output


def test_occ3d_grid_is_defined_once() -> None:
    """The occ3d and openocc-v2 presets are `occdata.constants.GRID` itself, and the CLI's `--range` help
    says its range: changing GRID changes all of them."""
    assert GRID_PRESETS["occ3d"].grid is GRID and GRID_PRESETS["openocc-v2"].grid is GRID
    words = " ".join(f"{v:g}" for v in (*GRID.lower, *GRID.upper))
    for command in ("labels", "build", "synth"):
        out = CliRunner().invoke(main, [command, "--help"], terminal_width=400).output
        assert f"default Occ3D's {words})" in out, command
