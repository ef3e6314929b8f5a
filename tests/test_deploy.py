"""Deployment: ONNX export parity (ONNX Runtime vs the PyTorch network), a standard-operator graph, the
streaming Predictor (shared preprocessing with the loader, fixed-size state) and clear errors on bad input."""

from __future__ import annotations

import json
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fastocc.checkpoint import CheckpointError, save_checkpoint
from fastocc.deploy import (
    DeployError,
    ExportConfig,
    Predictor,
    Rig,
    export_model,
    export_onnx,
    load_rig,
    synthetic_rig,
)
from fastocc.deploy.export import custom_domain_ops
from fastocc.model import FastOcc, HeadKind, preset
from occdata.constants import CAMERA_ORDER, CLASS_NAMES

REPO = Path(__file__).resolve().parents[1]

pytest.importorskip("onnxruntime")


def _checkpoint(path: Path, name: str = "nano", seed: int = 0, **overrides: object) -> Path:
    torch.manual_seed(seed)
    cfg = preset(name, **overrides)
    return save_checkpoint(path, cfg, FastOcc(cfg).state_dict())


def _values(state: tuple | dict) -> list[torch.Tensor]:  # noqa: ANN001 - a queue's or a recurrent state
    return list(state.values()) if isinstance(state, dict) else list(state)


def _frames(rig, n: int, seed: int = 0) -> list[list[np.ndarray]]:  # noqa: ANN001
    rng = np.random.default_rng(seed)
    return [[rng.integers(0, 256, (int(h), int(w), 3), dtype=np.uint8) for w, h in rig.image_size] for _ in range(n)]


def _poses(n: int) -> list[np.ndarray]:
    out = []
    for t in range(n):
        T = np.eye(4)
        a = 0.03 * t
        T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        T[:3, 3] = [500.0 + 1.2 * t, -300.0 + 0.1 * t, 0.0]
        out.append(T)
    return out


@pytest.fixture(scope="module")
def nano_export(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """nano / FastOcc head exported through the CLI: (checkpoint, onnx, stdout)."""
    d = tmp_path_factory.mktemp("export")
    ckpt = _checkpoint(d / "nano.pt")
    out = d / "nano.onnx"
    proc = subprocess.run([sys.executable, "-m", "cli.fastocc_cli", "export", "--checkpoint", str(ckpt), "--out",
                           str(out)], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return ckpt, out, proc.stdout


def test_cli_export_writes_a_parity_checked_standard_graph(nano_export: tuple[Path, Path, str]) -> None:
    import onnx

    ckpt, out, stdout = nano_export
    assert "PASS" in stdout and "parity" in stdout
    assert custom_domain_ops(out) == []
    ops = {n.op_type for n in onnx.load(str(out)).graph.node}
    assert {"ScatterND", "Gather", "Conv"} <= ops  # LSS pooling and interpolation sampling, standard ops
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["inputs"] == {"images": {"shape": [1, 6, 3, 128, 352], "dtype": "float32"}}
    assert meta["outputs"]["semantics"]["shape"] == [1, 200, 200, 16]
    assert meta["camera_order"] == list(CAMERA_ORDER) and meta["class_names"] == list(CLASS_NAMES)
    assert len(meta["class_colors"]) == 18 and meta["normalisation"]["colour_order"] == "RGB"
    assert meta["rig_hash"] == synthetic_rig().hash((128, 352))
    p = meta["parity"]
    assert p["passed"] and p["max_abs_diff"] <= 1e-3 and p["min_agreement"] >= 0.999
    from occdata.fileio import current_umask

    for f in (out, out.with_suffix(".json")):  # the mode open() gives under the umask (issue 17)
        assert stat.S_IMODE(f.stat().st_mode) == 0o666 & ~current_umask(), (f, oct(f.stat().st_mode))


@pytest.mark.parametrize("head", [HeadKind.FCN3D, HeadKind.DECONV])
def test_export_parity_baseline_heads_nano(tmp_path: Path, head: HeadKind) -> None:
    rep = export_onnx(ExportConfig(checkpoint=_checkpoint(tmp_path / "c.pt", head=head), out=tmp_path / "m.onnx"))
    assert rep.parity.passed and rep.parity.max_abs_diff <= 1e-3 and rep.parity.min_agreement >= 0.999
    assert custom_domain_ops(rep.out) == []


def test_export_refuses_a_graph_that_fails_parity(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Corrupt the baked interpolation weights: ONNX Runtime no longer matches PyTorch, nothing is written."""
    import fastocc.deploy.static as static

    real = static._slot_sampling

    def wrong(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        return [(rows, wts * 3.0, scatter) for rows, wts, scatter in real(*args, **kwargs)]

    monkeypatch.setattr(static, "_slot_sampling", wrong)
    torch.manual_seed(0)
    model = FastOcc(preset("nano"))
    with pytest.raises(DeployError, match="parity check failed"):
        export_model(model, synthetic_rig(), ExportConfig(checkpoint=Path("x"), out=tmp_path / "m.onnx", frames=1))
    assert list(tmp_path.iterdir()) == []


def test_custom_domain_ops_are_found(tmp_path: Path) -> None:
    import onnx
    from onnx import TensorProto, helper

    node = helper.make_node("Inverse", ["x"], ["y"], domain="com.microsoft")
    graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [4, 4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [4, 4])])
    onnx.save(helper.make_model(graph), str(tmp_path / "c.onnx"))
    assert custom_domain_ops(tmp_path / "c.onnx") == ["com.microsoft::Inverse"]


def test_predictor_onnx_matches_checkpoint(nano_export: tuple[Path, Path, str]) -> None:
    ckpt, onnx_path, _ = nano_export
    p_torch, p_onnx = Predictor(ckpt), Predictor(onnx_path)
    assert p_onnx.camera_order == CAMERA_ORDER
    for images in _frames(synthetic_rig(), 2):
        a = p_torch(images)
        b, probs = p_onnx(images, with_probs=True)
        assert a.shape == b.shape == (200, 200, 16) and a.dtype == b.dtype == np.uint8
        assert len(np.unique(a)) > 1  # a constant prediction would make agreement meaningless
        assert (a == b).mean() >= 0.999
        assert probs.shape == (18, 200, 200, 16)
        np.testing.assert_allclose(probs.sum(0), 1.0, atol=1e-5)
        assert (probs.argmax(0) == b).mean() >= 0.999


# Each fusion runs one of the two temporal deploy tests by default (about 50 s each); the other pairing is slow.
@pytest.mark.parametrize(("fusion", "queue_shape"), [("concat", (2, 16 * 8)),
                                                    pytest.param("cached", (2, 16), marks=pytest.mark.slow),
                                                    ("recurrent", (1, 32))])  # the measured default widths
def test_temporal_stream_parity_and_fixed_state(tmp_path: Path, fusion: str, queue_shape: tuple[int, int]) -> None:
    """A temporal nano: exported step with the queue as inputs/outputs; the Predictor keeps it. ONNX and
    PyTorch agree over a moving stream, and the state keeps its size whatever the stream length. The
    "cached" queue holds each frame reduced to C_r = 16 channels, the "concat" one the full C2 * 8 = 128,
    the "recurrent" history is its one state of C_r channels."""
    ckpt = _checkpoint(tmp_path / "t.pt", num_history=2, temporal_fusion=fusion)
    rep = export_onnx(ExportConfig(checkpoint=ckpt, out=tmp_path / "t.onnx", frames=3))
    assert rep.parity.passed and rep.parity.frames == 3
    meta = json.loads(rep.sidecar.read_text())
    assert meta["inputs"]["history"]["shape"] == [1, *queue_shape, 100, 100]
    assert meta["outputs"]["history_out"]["shape"] == [1, *queue_shape, 100, 100]
    assert meta["inputs"]["T_prev_from_cur"]["shape"] == [1, queue_shape[0], 4, 4]
    assert meta["temporal"]["fusion"] == fusion and meta["model_config"]["temporal_fusion"] == fusion
    assert set(meta["inputs"]) == {"images", "history", "T_prev_from_cur", "seq_start"}
    p_torch, p_onnx = Predictor(ckpt), Predictor(rep.out)
    with pytest.raises(DeployError, match="ego_pose"):
        p_onnx(_frames(synthetic_rig(), 1)[0])
    from fastocc.checkpoint import load_model

    p_static = Predictor.from_model(load_model(ckpt)[0], runtime="static")  # the export wrapper in PyTorch
    frames, poses = _frames(synthetic_rig(), 3, seed=1), _poses(5)
    sizes = []
    for t, pose in enumerate(poses):
        a = p_torch(frames[t % 3], pose)
        b = p_onnx(frames[t % 3], pose)
        assert (a == b).mean() >= 0.999, t
        assert (a == p_static(frames[t % 3], pose)).mean() >= 0.999, t
        st = p_onnx._backend.state
        q = p_torch._backend.model.temporal.queue_state()
        sizes.append((st.history.shape, len(st.poses), str([tuple(v.shape) for v in _values(q)])))
    assert len(set(sizes)) == 1 and sizes[0][1] == queue_shape[0]


def test_zero_history_fusion_exports_without_a_queue(tmp_path: Path) -> None:
    """The fusion-layer control (hist0fuse): the fusion layer is in the graph, no history inputs."""
    rep = export_onnx(ExportConfig(checkpoint=_checkpoint(tmp_path / "z.pt", zero_history_fusion=True),
                                   out=tmp_path / "z.onnx", frames=1))
    assert rep.parity.passed
    meta = json.loads(rep.sidecar.read_text())
    assert set(meta["inputs"]) == {"images"} and meta["model_config"]["zero_history_fusion"] is True


def _lane_rig(reader, i: int) -> Rig:  # noqa: ANN001
    """The fixed rig a Predictor streaming from sample i on would use: sample i's calibration."""
    return Rig(K=reader.small("calib/K")[i].astype(np.float64),
               T_keyego_from_cam=reader.small("calib/T_keyego_from_cam")[i].astype(np.float64),
               image_size=reader.small("cam/image_size")[i].astype(np.int64), cameras=CAMERA_ORDER,
               source=f"store sample {i}")


def _lanes(store: Path, model: FastOcc) -> tuple[dict[int, torch.Tensor], list[list[tuple[int, bool]]]]:
    """The training loader's scene-sequential batches (2 lanes, test transform) through the network in eval
    mode: class log-probabilities per store index, and each lane's (index, seq_start) stream in order.

    A Predictor holds one rig per stream, while the store's extrinsics move a little from frame to frame
    (camera vs keyframe time); so each row's calibration is held at its sequence's first sample, the rig
    the Predictor streams with. Images, poses, augmentation and the queue are the loader's."""
    from dataclasses import replace

    from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, make_loader
    from occdata.store.reader import open_store

    reader = open_store(store)
    H, W = model.cfg.input_hw
    sample = SampleConfig(image=ImageAugConfig(H, W, train=False), bev=BevAugConfig(train=False))
    loader = make_loader(LoaderConfig(store=store, batch_size=2, sequential=True, sample=sample))
    loader.dataset.set_epoch(0)
    probs: dict[int, torch.Tensor] = {}
    lanes: list[list[tuple[int, bool]]] = [[], []]
    rigs: dict[int, Rig] = {}
    model.clear_caches()
    with torch.no_grad():
        for batch in loader:
            rows = list(zip(batch.sample_index.tolist(), batch.seq_start.tolist(), strict=True))
            for row, (idx, start) in enumerate(rows):
                if start:
                    rigs[row] = _lane_rig(reader, idx)
                lanes[row].append((idx, start))
            inputs = batch.inputs()
            K = torch.stack([torch.as_tensor(rigs[r].K, dtype=torch.float32) for r in range(len(rows))])
            T = torch.stack([torch.as_tensor(rigs[r].T_keyego_from_cam, dtype=torch.float32) for r in range(len(rows))])
            out = model(replace(inputs, K=K, T_keyego_from_cam=T)).voxel_logits.float().log_softmax(1)
            for row, (idx, _) in enumerate(rows):
                probs[idx] = out[row]
    model.clear_caches()
    return probs, lanes


@pytest.mark.parametrize("fusion", [pytest.param("concat", marks=pytest.mark.slow), "cached",
                                    pytest.param("recurrent", marks=pytest.mark.slow)])
def test_scene_order_training_forward_equals_the_streaming_predictor(synth_store: Path, fusion: str) -> None:
    """What training computes on scene-ordered lanes (batch 2, each lane its own queue, float32 global poses)
    equals what the Predictor computes streaming each lane frame by frame (raw images, float64 poses),
    through the network itself and through the export wrapper."""
    from fastocc.checkpoint import load_model
    from occdata.store.reader import open_store

    ckpt = _checkpoint(synth_store.parent / f"lanes-{fusion}.pt", num_history=2, temporal_fusion=fusion,
                       input_hw=(96, 256))
    model = load_model(ckpt)[0]
    probs, lanes = _lanes(synth_store, model)
    reader = open_store(synth_store)
    poses = reader.small("pose/T_global_from_keyego")
    assert sum(len(lane) for lane in lanes) == len(probs) == len(reader.done_indices()) >= 6
    assert sum(not start for lane in lanes for _, start in lane) >= 4  # frames that use their history
    worst = 0.0
    for runtime in ("torch", "static"):
        for lane in lanes:
            pred = Predictor.from_model(load_model(ckpt)[0], _lane_rig(reader, lane[0][0]), runtime=runtime)
            for idx, start in lane:
                sem, p = pred(reader.images(idx), poses[idx], seq_start=start, with_probs=True)
                diff = float((torch.from_numpy(p).log() - probs[idx]).abs().max())  # = logits up to a constant
                worst = max(worst, diff)
                assert diff < 1e-4, (runtime, idx, diff)
                assert (sem == probs[idx].argmax(0).numpy()).mean() >= 0.999, (runtime, idx)
    # control: the history matters (a frame predicted without its past differs by far more than the above)
    idx = lanes[0][-1][0]
    alone = Predictor.from_model(load_model(ckpt)[0], _lane_rig(reader, lanes[0][0][0]))
    _, p = alone(reader.images(idx), poses[idx], seq_start=True, with_probs=True)
    effect = float((torch.from_numpy(p).log() - probs[idx]).abs().max())
    # measured (Intel Xeon VM): worst 1.2e-6 against the 1e-4 bound, effect 1.6e-3: margins of 80x and 1300x
    assert effect > 5e-4 and effect > 50 * worst


def test_loader_and_predictor_share_preprocessing(synth_store: Path) -> None:
    """The Predictor's input equals the loader's test-transform input bit for bit (same store images)."""
    from fastocc.data.augment import BevAugConfig, ImageAugConfig
    from fastocc.data.sample import SampleConfig, SampleMaker, StoreSamples
    from occdata.store.reader import open_store

    reader = open_store(synth_store)
    samples = StoreSamples(reader)
    test_cfg = SampleConfig(image=ImageAugConfig(128, 352, train=False), bev=BevAugConfig(train=False))
    maker = SampleMaker(samples, test_cfg)
    torch.manual_seed(0)
    rig = load_rig(synth_store)
    np.testing.assert_array_equal(rig.K.astype(np.float32), samples.K[0])
    np.testing.assert_array_equal(rig.T_keyego_from_cam.astype(np.float32), samples.T_keyego_from_cam[0])
    pred = Predictor.from_model(FastOcc(preset("nano")), rig)
    for i in (0, 2):
        loader = maker(samples.read_run(i, i + 1)[0], None)
        mine = pred.preprocess(reader.images(i))[0]
        np.testing.assert_array_equal(mine, loader["images"])
        np.testing.assert_allclose(pred.img_aug, loader["img_aug"])
    bgr = Predictor.from_model(FastOcc(preset("nano")), rig, bgr=True)
    np.testing.assert_array_equal(bgr.preprocess([im[..., ::-1] for im in reader.images(0)])[0],
                                  maker(samples.read_run(0, 1)[0], None)["images"])


def test_rig_from_tree_matches_rig_from_store(synth_root: Path, synth_store: Path) -> None:
    a, b = load_rig(synth_root), load_rig(synth_store)
    np.testing.assert_allclose(a.K, b.K)
    np.testing.assert_allclose(a.T_keyego_from_cam, b.T_keyego_from_cam, atol=1e-9)
    np.testing.assert_array_equal(a.image_size, b.image_size)
    assert a.cameras == b.cameras == CAMERA_ORDER
    assert a.hash((128, 352)) == b.hash((128, 352)) != synthetic_rig().hash((128, 352))


def test_bad_inputs_are_one_clear_error_each(tmp_path: Path, nano_export: tuple[Path, Path, str],
                                             synth_store: Path) -> None:
    ckpt, onnx_path, _ = nano_export
    bare = tmp_path / "bare.pt"
    torch.save(FastOcc(preset("nano")).state_dict(), bare)
    with pytest.raises(CheckpointError, match="not a fastocc checkpoint"):
        Predictor(bare)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable fastocc checkpoint"):
        export_onnx(ExportConfig(checkpoint=junk, out=tmp_path / "x.onnx"))
    with pytest.raises(DeployError, match="has 5 cameras but the model expects 6"):
        Predictor.from_model(FastOcc(preset("nano")), synthetic_rig(5))
    with pytest.raises(DeployError, match="has 6 cameras but the model expects 5"):
        export_model(FastOcc(preset("nano", num_cams=5)), synthetic_rig(), ExportConfig(Path("c"), tmp_path / "y.onnx"))
    with pytest.raises(DeployError, match="must end in .onnx"):
        export_model(FastOcc(preset("nano")), synthetic_rig(), ExportConfig(Path("c"), tmp_path / "y.bin"))
    with pytest.raises(DeployError, match="exported for another rig"):
        Predictor(onnx_path, rig=synth_store)
    pred = Predictor(onnx_path)
    images = _frames(synthetic_rig(), 1)[0]
    with pytest.raises(DeployError, match="expected 6 camera images"):
        pred(images[:5])
    with pytest.raises(DeployError, match=r"expected a \(900, 1600, 3\) image"):
        pred([*images[:5], images[5][:450, :800]])
    with pytest.raises(DeployError, match="must be uint8"):
        pred([*images[:5], images[5].astype(np.float32)])
    (tmp_path / "lonely.onnx").write_bytes(onnx_path.read_bytes())
    with pytest.raises(DeployError, match="no sidecar"):
        Predictor(tmp_path / "lonely.onnx")
    assert list(tmp_path.glob("*.onnx")) == [tmp_path / "lonely.onnx"]  # no failed export left a file


def test_cli_export_bad_checkpoint_is_one_line(tmp_path: Path) -> None:
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"nope")
    proc = subprocess.run([sys.executable, "-m", "cli.fastocc_cli", "export", "--checkpoint", str(junk), "--out",
                           str(tmp_path / "m.onnx")], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    assert proc.stderr.strip().startswith("Error:") and "Traceback" not in proc.stderr
    assert "not a readable fastocc checkpoint" in proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("head", list(HeadKind))
def test_export_parity_tiny(tmp_path: Path, head: HeadKind) -> None:
    rep = export_onnx(ExportConfig(checkpoint=_checkpoint(tmp_path / "c.pt", "tiny", head=head),
                                   out=tmp_path / "m.onnx"))
    assert rep.parity.passed and rep.parity.max_abs_diff <= 1e-3 and rep.parity.min_agreement >= 0.999
    assert custom_domain_ops(rep.out) == []
    # Its speed (the 2-minute target) is measured in docs/deploy.md, not asserted here.


@pytest.mark.slow
def test_runtime_bench_all_runtimes_nano() -> None:
    from fastocc.bench import RuntimeBenchConfig, format_runtime_report, run_runtime_benchmark

    res = run_runtime_benchmark(RuntimeBenchConfig(preset="nano", repeats=1, warmup=0))
    assert set(res["runtimes"]) == {"torch", "compile", "onnx"}
    for r in res["runtimes"].values():
        assert r["ms"] > 0 and r["argmax_agreement_percent"] >= 99.9
    assert "onnx" in format_runtime_report(res)


def test_predictor_is_exported_from_the_package() -> None:
    import fastocc

    assert fastocc.Predictor is Predictor and "Predictor" in fastocc.__all__


def test_rig_from_the_real_nuscenes_sample(real_nuscenes_root: Path) -> None:
    """K per camera against calibrated_sensor.json read directly; the real front camera looks forward."""
    rig = load_rig(real_nuscenes_root)
    tables = real_nuscenes_root / "v1.0-mini"
    channel = {s["token"]: s["channel"] for s in json.loads((tables / "sensor.json").read_text())}
    K = {channel[c["sensor_token"]]: c["camera_intrinsic"] for c in json.loads((tables / "calibrated_sensor.json")
                                                                               .read_text())}
    assert rig.cameras == CAMERA_ORDER
    for n, cam in enumerate(rig.cameras):
        np.testing.assert_allclose(rig.K[n], K[cam])
    front = rig.T_keyego_from_cam[CAMERA_ORDER.index("CAM_FRONT")]
    assert front[:3, 2] @ np.array([1.0, 0.0, 0.0]) > 0.99  # optical axis along ego +x
    assert rig.image_size.tolist() == [[1600, 900]] * 6


def test_export_for_a_store_rig_and_stream_its_frames(tmp_path: Path, synth_store: Path) -> None:
    """The issue's user story: export for the store's rig, then run the Predictor on the store's frames."""
    from occdata.store.reader import open_store

    ckpt = _checkpoint(tmp_path / "c.pt")
    rep = export_onnx(ExportConfig(checkpoint=ckpt, out=tmp_path / "store.onnx", rig=synth_store, frames=1))
    meta = json.loads(rep.sidecar.read_text())
    assert meta["rig"]["image_size"] == [[400, 225]] * 6 and "store" in meta["rig"]["source"]
    reader = open_store(synth_store)
    p_onnx, p_torch = Predictor(rep.out, rig=synth_store), Predictor(ckpt, rig=synth_store)
    poses = reader.small("pose/T_global_from_keyego")
    for i in reader.done_indices():
        a = p_onnx(reader.images(int(i)), poses[i])
        assert (a == p_torch(reader.images(int(i)), poses[i])).mean() >= 0.999
    with pytest.raises(DeployError, match=r"expected a \(225, 400, 3\) image"):
        p_onnx(_frames(synthetic_rig(), 1)[0])
