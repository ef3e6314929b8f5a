"""Other rigs through the whole chain, at small sizes: `occdata synth --rig lyft|truckscenes` -> scan ->
labels -> build (with the generated labels) -> `fastocc train` (2 steps) -> eval -> export (ONNX, the
rig baked in) -> predict. The rigs differ from nuScenes in camera count and names, image size, LiDAR
count, file formats and table quirks (docs/synth.md); nothing here knows nuScenes' six cameras."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.fastocc_cli import main as fastocc_main
from cli.occdata_cli import main as occdata_main
from fastocc.train.config import load_config
from fastocc.train.loop import train
from occdata.store.reader import open_store

RIGS = {  # rig -> (cameras, LiDARs) of its synthetic world
    "lyft": (7, 3),
    "truckscenes": (4, 6),
}
TINY = {"preset": "nano", "input_hw": [64, 176], "epochs": 1, "lr": 2e-3, "lr_scaling": "none", "workers": 0,
        "threads": 1, "log_every": 1, "val_every": 0, "keep_epochs": 1, "limit_train_samples": 2}


def _ok(main, args: list[str]) -> str:  # noqa: ANN001 - a click group
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, (args[0], res.output)
    return res.output


@pytest.fixture(scope="module", params=sorted(RIGS))
def chain(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path | str]:
    rig = request.param
    d = tmp_path_factory.mktemp(rig)
    world, gts, store = d / "world", d / "gts", d / "data.zarr"
    _ok(occdata_main, ["synth", "--rig", rig, "--out", str(world), "--scenes", "2", "--samples", "3",
                       "--width", "192", "--height", "108", "--seed", "3", "--no-progress"])
    scan = json.loads(_ok(occdata_main, ["scan", "--root", str(world), "--json"]))
    _ok(occdata_main, ["labels", "--root", str(world), "--out", str(gts), "--no-progress"])
    _ok(occdata_main, ["build", "--root", str(world), "--gts", str(gts / "occ3d") if (gts / "occ3d").is_dir()
                       else str(gts), "--out", str(store), "--no-progress"])
    return {"rig": rig, "world": world, "store": store, "scan": json.dumps(scan), "dir": d}


def test_scan_and_build_hold_the_rig(chain: dict) -> None:
    n_cams, n_lidars = RIGS[chain["rig"]]
    scan = json.loads(chain["scan"])
    assert len(scan["rig"]["cameras"]) == n_cams and len(scan["rig"]["lidars"]) == n_lidars
    reader = open_store(chain["store"])
    assert reader.n_cams == n_cams and reader.attrs["rig"] == scan["rig"]
    assert reader.group["labels/present"][:].all()  # every keyframe labelled by occdata labels


def test_train_eval_export_predict(chain: dict) -> None:
    pytest.importorskip("onnxruntime")
    from fastocc.deploy import ExportConfig, Predictor, export_onnx

    n_cams, _ = RIGS[chain["rig"]]
    run = chain["dir"] / "run"
    reader = open_store(chain["store"])
    split = reader.attrs["splits"][0]
    res = train(load_config(None, {**TINY, "store": str(chain["store"]), "out": str(run), "train_split": split,
                                   "val_split": split}), progress=False)
    assert res.opt_steps == 2
    ckpt = run / "last.pt"
    out = _ok(fastocc_main, ["eval", "--checkpoint", str(ckpt), "--store", str(chain["store"]), "--split", split,
                             "--json", "--no-progress"])
    report = json.loads(out[out.index("{"):])
    assert report["n_samples"] == len(reader.split_indices(split)) and 0.0 <= report["miou"] <= 100.0
    rep = export_onnx(ExportConfig(checkpoint=ckpt, out=chain["dir"] / "m.onnx", rig=chain["store"], frames=1))
    assert rep.parity.passed
    meta = json.loads(rep.sidecar.read_text())
    assert meta["camera_order"] == reader.attrs["camera_order"] and len(meta["rig"]["image_size"]) == n_cams
    pred = Predictor(rep.out)
    occ = pred(reader.images(0))
    assert occ.shape == (200, 200, 16)
    _ok(fastocc_main, ["predict", "--checkpoint", str(ckpt), "--store", str(chain["store"]), "--split", split,
                       "--out", str(chain["dir"] / "pred"), "--no-progress"])
    assert len(list((chain["dir"] / "pred").glob("*/*/labels.npz"))) == len(reader.split_indices(split))
