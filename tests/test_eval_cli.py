"""`occdata eval` on the synthetic store: its own ground truth scores 100, every bad input one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.occdata_cli import main
from occdata.eval.metrics import MIoUAccumulator, RayIoUAccumulator
from occdata.eval.rays import scene_ray_origins
from occdata.store.reader import open_store


def _cli(*args: str) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.output


def _val_gts(synth_root: Path, synth_store: Path) -> list[tuple[str, str, Path]]:
    """(scene, token, label file) of every val sample of the synthetic world."""
    reader = open_store(synth_store)
    scenes = [s["name"] for s in reader.attrs["scenes"] if s["split"] == "val"]
    return [(s, p.name, p / "labels.npz") for s in scenes for p in sorted((synth_root / "gts" / s).iterdir())]


@pytest.fixture
def occ3d_pred(synth_root: Path, synth_store: Path, tmp_path: Path) -> Path:
    """The val ground truth copied as predictions in the Occ3D layout."""
    out = tmp_path / "pred"
    for scene, token, label in _val_gts(synth_root, synth_store):
        (out / scene / token).mkdir(parents=True)
        shutil.copy(label, out / scene / token / "labels.npz")
    return out


def _eval_json(pred: Path, store: Path, *extra: str) -> dict:
    code, out = _cli("eval", "--pred", str(pred), "--store", str(store), "--json", "--no-progress", *extra)
    assert code == 0, out
    return json.loads(out)


def test_eval_own_ground_truth_scores_100(occ3d_pred: Path, synth_store: Path) -> None:
    r = _eval_json(occ3d_pred, synth_store)
    assert r["n_samples"] == 3 and r["split"] == "val" and r["mask"] == "camera"
    assert r["miou"] == 100.0 and r["geo_iou"] == 100.0
    assert r["rayiou"] == 100.0 and r["rayiou_at"] == {"1": 100.0, "2": 100.0, "4": 100.0}
    seen = [c for c, v in r["per_class"].items() if v["rayiou@1"] is not None]
    assert len(seen) >= 5  # many classes are really seen by the rays
    code, out = _cli("eval", "--pred", str(occ3d_pred), "--store", str(synth_store), "--no-progress")
    assert code == 0 and "RayIoU@4" in out and "mIoU 100.00" in out and "RayIoU 100.00" in out


def test_eval_flat_layout_with_pred_key(synth_root: Path, synth_store: Path, tmp_path: Path) -> None:
    flat = tmp_path / "flat"
    flat.mkdir()
    for _, token, label in _val_gts(synth_root, synth_store):
        np.savez(flat / f"{token}.npz", pred=np.load(label, allow_pickle=False)["semantics"])
    r = _eval_json(flat, synth_store, "--mask", "none", "--no-rayiou")
    assert r["miou"] == 100.0 and "rayiou" not in r


def test_eval_scores_a_changed_prediction_like_the_accumulators(occ3d_pred: Path, synth_store: Path) -> None:
    """Shift one sample's prediction by one voxel along x: the command's numbers equal the
    accumulators fed directly from the store (the wiring: masks, origins, split, order)."""
    files = sorted(occ3d_pred.glob("*/*/labels.npz"))
    sem = np.load(files[0], allow_pickle=False)["semantics"]
    shifted = np.roll(sem, 1, axis=0)
    np.savez_compressed(files[0], semantics=shifted)
    r = _eval_json(occ3d_pred, synth_store, "--mask", "lidar")
    reader = open_store(synth_store)
    miou, ray = MIoUAccumulator(), RayIoUAccumulator()
    for i in range(reader.n_samples):
        if reader.attrs["splits"][reader.small("sample/split")[i]] != "val":
            continue
        a = reader.sample_arrays(i, ("labels/semantics", "labels/mask_lidar"))
        pred = shifted if reader.token(i) == files[0].parent.name else a["labels/semantics"]
        miou.update(a["labels/semantics"], pred, a["labels/mask_lidar"])
        ray.update(a["labels/semantics"], pred, scene_ray_origins(reader, i))
    assert r["miou"] == pytest.approx(100 * miou.result().miou, abs=1e-3) and r["miou"] < 100
    assert r["rayiou"] == pytest.approx(100 * ray.result().rayiou, abs=1e-3) and r["rayiou"] < 100


def _one_line_error(pred: Path, store: Path, *extra: str) -> str:
    code, out = _cli("eval", "--pred", str(pred), "--store", str(store), "--no-progress", *extra)
    assert code == 1, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), out
    return lines[0]


@pytest.mark.parametrize("bad", ["missing", "shape", "dtype", "range", "unknown", "corrupt", "key", "scene"])
def test_eval_bad_predictions_give_one_line(bad: str, occ3d_pred: Path, synth_store: Path) -> None:
    files = sorted(occ3d_pred.glob("*/*/labels.npz"))
    target = files[1]
    sem = np.load(target, allow_pickle=False)["semantics"]
    expect = {"missing": "1 of 3 labelled 'val' samples have no prediction",
              "shape": "semantics has shape (200, 200, 8)", "dtype": "dtype float32",
              "range": "values outside 0..17", "unknown": "tokens not in store",
              "corrupt": "not a readable .npz", "key": "no 'semantics' or 'pred'", "scene": "belongs to scene"}[bad]
    if bad == "missing":
        shutil.rmtree(target.parent)
        expect_name = target.parent.name
    else:
        expect_name = target.name
    if bad == "shape":
        np.savez(target, semantics=sem[:, :, :8])
    elif bad == "dtype":
        np.savez(target, semantics=sem.astype(np.float32))
    elif bad == "range":
        sem = sem.copy()
        sem[0, 0, 0] = 18
        np.savez(target, semantics=sem)
    elif bad == "unknown":
        np.savez(occ3d_pred / ("f" * 32 + ".npz"), pred=sem)
        expect_name = "f" * 32
    elif bad == "corrupt":
        target.write_bytes(b"not a zip file")
    elif bad == "key":
        np.savez(target, labels=sem)
    elif bad == "scene":
        wrong = occ3d_pred / "scene-9999" / target.parent.name
        wrong.parent.mkdir()
        shutil.move(str(target.parent), str(wrong))
        expect_name = "scene-9999"
    line = _one_line_error(occ3d_pred, synth_store)
    assert expect in line and expect_name in line


def test_eval_bad_split_and_store(occ3d_pred: Path, synth_store: Path, tmp_path: Path) -> None:
    assert "split 'test' is not in store" in _one_line_error(occ3d_pred, synth_store, "--split", "test")
    assert "store not found" in _one_line_error(occ3d_pred, tmp_path / "nope.zarr")
    assert "prediction folder not found" in _one_line_error(tmp_path / "nothing", synth_store)
    (tmp_path / "empty").mkdir()
    assert "no predictions in" in _one_line_error(tmp_path / "empty", synth_store)


def test_eval_reads_the_store_block_by_block(synth_root: Path, occ3d_pred: Path, tmp_path: Path) -> None:
    """A store with 2-sample shards: the val samples span several blocks; all are scored once."""
    from occdata.store.build import BuildConfig, build_store

    store = tmp_path / "small_blocks.zarr"
    build_store(BuildConfig(root=synth_root, out=store, gts=synth_root / "gts", block_samples=2, progress=False))
    r = _eval_json(occ3d_pred, store)
    assert r["n_samples"] == 3 and r["miou"] == 100.0 and r["rayiou"] == 100.0


def test_eval_unlabelled_split(synth_root: Path, occ3d_pred: Path, tmp_path: Path) -> None:
    """A store built without labels: the split exists but has nothing to score."""
    from occdata.store.build import BuildConfig, build_store

    store = tmp_path / "nolabels.zarr"
    build_store(BuildConfig(root=synth_root, out=store, gts=None, progress=False))
    assert "has no labelled samples" in _one_line_error(occ3d_pred, store)
