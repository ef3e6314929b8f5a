"""OpenOcc v2 flow carried into the store: `occdata build --gts` on a tree whose files carry `flow`.

The labels come from `occdata labels --grid openocc-v2` on the session's synthetic world; the store
must hold their flow exactly, their classes in our ids, and say so (schema 3, `attrs["flow"]`); a store
from Occ3D files must stay as it was before flow existed (schema 2, the same attributes and arrays).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.constants import GRID
from occdata.errors import OccDataError
from occdata.formats.gridspec import GRID_PRESETS, custom_grid
from occdata.formats.occ3d import openocc_to_occ3d, read_label, read_openocc_v2_label
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.nuscenes import load_nuscenes
from occdata.store.build import BuildConfig, build_store
from occdata.store.commands.info import dump_sample, store_info
from occdata.store.commands.verify import verify_store
from occdata.store.create import root_attrs
from occdata.store.reader import open_store

# The checksum columns of every store built before flow existed (schema 2): they must not move.
PRE_FLOW_CHECKSUM_ARRAYS = [
    "sample/token", "sample/scene_index", "sample/split", "sample/index_in_scene", "sample/timestamp",
    "sample/lidar_token", "cam/token", "cam/timestamp", "cam/image_size", "calib/K", "calib/T_ego_from_cam",
    "calib/T_keyego_from_cam", "calib/T_ego_from_lidar", "pose/T_global_from_keyego", "pose/T_global_from_ego_cam",
    "temporal/prev_index", "temporal/prev_valid", "images/offsets", "depth/offsets", "labels/present",
    "labels/semantics", "labels/mask_lidar", "labels/mask_camera", "labels/bev", "visibility/present",
    "visibility/camera", "visibility/lidar", "images/jpeg", "depth/uvd",
]


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


@pytest.fixture(scope="module")
def labelled(synth_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`occdata labels --grid occ3d --grid openocc-v2` output of the session world."""
    out = tmp_path_factory.mktemp("flowlabels") / "labels"
    generate_labels(LabelsConfig(root=synth_root, out=out, options=LabelOptions(), progress=False,
                                 grids=(GRID_PRESETS["occ3d"], GRID_PRESETS["openocc-v2"])))
    return out


@pytest.fixture(scope="module")
def flow_store(synth_root: Path, labelled: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("flowstore") / "flow.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=labelled / "openocc-v2", block_samples=2, progress=False))
    return out


def _label_file(root: Path, reader, i: int) -> Path:  # noqa: ANN001
    scene = reader.attrs["scenes"][int(reader.small("sample/scene_index")[i])]["name"]
    return root / scene / reader.token(i) / "labels.npz"


def test_store_holds_the_files_flow_and_their_classes_in_our_ids(flow_store: Path, labelled: Path) -> None:
    reader = open_store(flow_store)
    assert reader.has_flow and reader.attrs["schema_version"] == 3
    assert reader.attrs["checksum_arrays"] == [*PRE_FLOW_CHECKSUM_ARRAYS, "labels/flow"]
    assert reader.attrs["flow"]["unit"] == "m/s" and reader.attrs["build_identity"]["labels_format"] == "openocc-v2"
    assert reader.group["labels/flow"].shape == (reader.n_samples, 200, 200, 16, 2)
    moving = 0
    for i in range(reader.n_samples):
        with np.load(_label_file(labelled / "openocc-v2", reader, i)) as f:
            flow, sem_openocc = f["flow"], f["semantics"]
        a = reader.sample_arrays(i)
        np.testing.assert_array_equal(a["labels/flow"], flow)  # float32 in, float32 stored: exact
        # The class ids went back to ours: the same grid as the occ3d output (the world has lidarseg, so
        # no "others" was folded into free) and as the name map of the file's own ids.
        np.testing.assert_array_equal(a["labels/semantics"], read_label(_label_file(labelled, reader, i))["semantics"])
        np.testing.assert_array_equal(a["labels/semantics"], openocc_to_occ3d()[sem_openocc])
        moving += int((np.abs(flow) > 0.5).any(axis=-1).sum())
    assert moving > 100, "the world must have moving objects for this test to mean anything"


def test_flow_store_verifies_reports_and_dumps(flow_store: Path, tmp_path: Path) -> None:
    reader = open_store(flow_store)
    assert verify_store(reader) == []
    info = store_info(reader)
    assert info["flow"] is True and "labels/flow" in info["arrays"]
    code, text = _cli("info", "--store", str(flow_store))
    assert code == 0 and "flow: labels/flow" in text and "schema occdata.store v3" in text
    keys = dump_sample(reader, 0, tmp_path / "s.npz")
    assert "flow" in keys
    with np.load(tmp_path / "s.npz") as d:
        np.testing.assert_array_equal(d["flow"], reader.sample_arrays(0, ("labels/flow",))["labels/flow"])


def test_damaged_flow_is_caught(flow_store: Path, tmp_path: Path) -> None:
    copy = tmp_path / "c.zarr"
    shutil.copytree(flow_store, copy)
    g = zarr.open_group(str(copy), mode="r+")
    row = np.asarray(g["labels/flow"][1])
    i, j, k = np.argwhere(np.abs(row).sum(-1) > 0)[0]
    row[i, j, k] += 1.0
    g["labels/flow"][1] = row  # as a flipped byte would: no checksum update
    problems = verify_store(open_store(copy))
    assert [(p.index, p.array, p.reason) for p in problems] == [(1, "labels/flow", "checksum mismatch")]
    with pytest.raises(OccDataError, match="labels/flow"):
        open_store(copy).sample_arrays(1, ("labels/flow",))
    shutil.rmtree(copy / "labels" / "flow" / "c")  # every shard gone: reads as zeros, caught all the same
    problems = verify_store(open_store(copy))
    assert {p.array for p in problems} == {"labels/flow"} and any("missing" in p.reason for p in problems)


def test_occ3d_store_is_unchanged_by_flow(synth_root: Path, labelled: Path, tmp_path: Path) -> None:
    out = tmp_path / "occ3d.zarr"
    build_store(BuildConfig(root=synth_root, out=out, gts=labelled, block_samples=2, progress=False))
    reader = open_store(out)
    assert not reader.has_flow and reader.attrs["schema_version"] == 2
    assert reader.attrs["checksum_arrays"] == PRE_FLOW_CHECKSUM_ARRAYS
    assert "flow" not in reader.attrs and "labels_format" not in reader.attrs["build_identity"]
    assert "flow" not in reader.group["labels"] and store_info(reader)["flow"] is False
    code, text = _cli("info", "--store", str(out))
    assert code == 0 and "flow: none" in text


def _mixed(labelled: Path, dst: Path, first_kind: str) -> Path:
    """A copy of one format's tree with one later file of the other format."""
    base = labelled / "openocc-v2" if first_kind == "openocc-v2" else labelled
    other = labelled if first_kind == "openocc-v2" else labelled / "openocc-v2"
    shutil.copytree(base, dst, ignore=shutil.ignore_patterns("openocc-v2", "labels.json", ".records"))
    last = sorted(dst.glob("*/*/labels.npz"))[-1]
    shutil.copyfile(other / last.relative_to(dst), last)
    return last


@pytest.mark.parametrize("first_kind", ["openocc-v2", "occ3d"])
def test_a_mixed_tree_is_one_clear_error(synth_root: Path, labelled: Path, tmp_path: Path, first_kind: str) -> None:
    odd = _mixed(labelled, tmp_path / "gts", first_kind)
    code, text = _cli("build", "--root", str(synth_root), "--gts", str(tmp_path / "gts"),
                      "--out", str(tmp_path / "m.zarr"), "--no-progress")
    assert code != 0
    err = text.strip().splitlines()[-1]
    assert str(odd) in err and "mixes the two formats" in err and "Traceback" not in text


def test_resume_with_the_other_format_is_refused(synth_root: Path, labelled: Path, flow_store: Path,
                                                  tmp_path: Path) -> None:
    copy = tmp_path / "f.zarr"
    shutil.copytree(flow_store, copy)
    with pytest.raises(OccDataError, match="format of the --gts files"):
        build_store(BuildConfig(root=synth_root, out=copy, gts=labelled, block_samples=2, progress=False,
                                resume=True))


def test_openocc_reader_refuses_an_occ3d_file_and_back(labelled: Path) -> None:
    occ3d_file = sorted(labelled.glob("*/*/labels.npz"))[0]
    openocc_file = labelled / "openocc-v2" / occ3d_file.relative_to(labelled)
    with pytest.raises(OccDataError, match="not an OpenOcc v2 file"):
        read_openocc_v2_label(occ3d_file)
    with pytest.raises(OccDataError, match="OpenOcc v2 file"):
        read_label(openocc_file)


def test_the_loader_reads_a_flow_store(flow_store: Path) -> None:
    from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, StoreDataset

    sample = SampleConfig(image=ImageAugConfig(train=False, height=128, width=352), bev=BevAugConfig(train=False))
    batch = next(iter(StoreDataset(LoaderConfig(store=flow_store, batch_size=2, sequential=True, sample=sample))))
    reader = open_store(flow_store)
    i = int(batch.sample_index[0])
    np.testing.assert_array_equal(batch.semantics[0].numpy(), reader.sample_arrays(i)["labels/semantics"])


# --- occdata eval: mAVE and OccScore --------------------------------------------------------------------------
def _eval(store: Path, pred: Path, *extra: str) -> dict:
    import json

    code, text = _cli("eval", "--pred", str(pred), "--store", str(store), "--split", "train", "--json",
                      "--no-progress", *extra)
    assert code == 0, text
    return json.loads(text)


def test_the_generators_flow_scores_itself_perfectly(flow_store: Path, labelled: Path) -> None:
    out = _eval(flow_store, labelled / "openocc-v2", "--pred-classes", "openocc-v2")
    assert out["rayiou"] == 100.0 and out["mave"] == 0.0 and out["occ_score"] == 100.0
    assert out["mave_unit"] == "m/s" and out["per_class"]["car"]["ave"] == 0.0
    assert "ave" not in out["per_class"]["manmade"]


def test_a_known_flow_error_is_the_mave(flow_store: Path, labelled: Path, tmp_path: Path) -> None:
    """Every predicted flow off by (0.3, 0.4): every true-positive ray errs by 0.5 m/s, so mAVE = 0.5 and
    OccScore = 0.9 x 1 + 0.1 x 0.5 = 95 (the classes and geometry are the truth's)."""
    src = labelled / "openocc-v2"
    for f in src.glob("*/*/labels.npz"):
        with np.load(f) as d:
            arrays = dict(d)
        arrays["flow"] = arrays["flow"] + np.array([0.3, 0.4], np.float32)
        dst = tmp_path / f.relative_to(src)
        dst.parent.mkdir(parents=True)
        np.savez(dst, **arrays)
    out = _eval(flow_store, tmp_path, "--pred-classes", "openocc-v2")
    assert out["rayiou"] == 100.0
    assert out["mave"] == pytest.approx(0.5, abs=1e-5) and out["occ_score"] == pytest.approx(95.0, abs=1e-4)
    code, text = _cli("eval", "--pred", str(tmp_path), "--store", str(flow_store), "--split", "train",
                      "--pred-classes", "openocc-v2", "--no-progress")
    assert code == 0 and "mAVE 0.500 m/s, OccScore 95.00" in text and "AVE m/s" in text


def test_without_flow_mave_is_not_available(flow_store: Path, synth_root: Path, labelled: Path,
                                            tmp_path: Path) -> None:
    out = _eval(flow_store, labelled)  # the occ3d output: no flow in the predictions
    assert out["mave"] is None and out["occ_score"] is None and "carry no 'flow'" in out["flow_note"]
    assert out["rayiou"] == 100.0
    code, text = _cli("eval", "--pred", str(labelled), "--store", str(flow_store), "--split", "train",
                      "--no-progress")
    assert code == 0
    assert [ln for ln in text.splitlines() if "mAVE" in ln] == [
        "mAVE, OccScore: not available (the predictions carry no 'flow' array)"]
    plain = tmp_path / "plain.zarr"  # a store without flow, predictions with flow
    build_store(BuildConfig(root=synth_root, out=plain, gts=labelled, block_samples=2, progress=False))
    out = _eval(plain, labelled / "openocc-v2", "--pred-classes", "openocc-v2")
    assert out["mave"] is None and "store has no flow" in out["flow_note"]


def test_predictions_mixing_flow_and_none_are_one_error(flow_store: Path, labelled: Path, tmp_path: Path) -> None:
    odd = _mixed(labelled, tmp_path / "pred", "openocc-v2")
    reader = open_store(flow_store)
    i = next(i for i in range(reader.n_samples) if reader.token(i) == odd.parent.name)
    split = reader.attrs["splits"][int(reader.small("sample/split")[i])]  # the odd file's split is scored
    code, text = _cli("eval", "--pred", str(tmp_path / "pred"), "--store", str(flow_store), "--split", split,
                      "--pred-classes", "openocc-v2", "--no-progress")
    assert code != 0 and "give every prediction a flow, or none" in text and str(odd) in text


def test_the_viewer_reads_the_flow_for_its_speed_view(flow_store: Path) -> None:
    from occdata.view.config import FrameOptions
    from occdata.view.frame import compose_frame
    from occdata.view.source import ViewSource

    src = ViewSource(flow_store)
    assert src.has_flow
    scene = src.scenes[0]
    s = src.sample(scene, 0, flow=True)
    stored = open_store(flow_store).sample_arrays(s.index, ("labels/flow",))["labels/flow"]
    np.testing.assert_array_equal(s.flow, stored)
    assert src.sample(scene, 0).flow is None  # only when asked
    (group,) = compose_frame(s, FrameOptions(view="speed")).groups
    assert any(layer.name.startswith("speed_") for layer in group.layers)  # the world's actors move


def test_the_flow_attribute_names_the_store_grid(synth_root: Path, flow_store: Path, tmp_path: Path) -> None:
    """`attrs["flow"]["shape"]` is labels/flow's shape on the store's own grid: Occ3D's as every flow store
    recorded it, and another grid's (a coarse OpenOcc v2-style one) its own."""
    reader = open_store(flow_store)
    words = reader.attrs["flow"]["shape"]
    assert words == "(N, 200, 200, 16, 2)" == f"(N, {', '.join(map(str, reader.group['labels/flow'].shape[1:]))})"
    ds = load_nuscenes(synth_root, None)
    coarse = custom_grid(0.8, GRID.lower, GRID.upper, base="openocc-v2")
    cfg = BuildConfig(root=synth_root, out=tmp_path / "coarse.zarr", grid=coarse, progress=False)
    assert root_attrs(cfg, ds, ["train"], None, "openocc-v2")["flow"]["shape"] == "(N, 100, 100, 8, 2)"
