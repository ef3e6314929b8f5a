"""`occdata labels` on a synthetic world with moving actors, scored against the world's exact labels.

The truth is independent of the generator: the synthetic world voxelises its primitives exactly
(occdata/synth/labels.py), while the generator only sees the LiDAR files, the box tables and lidarseg.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from occdata.errors import OccDataError
from occdata.labels import LabelOptions, LabelsConfig, generate_labels
from occdata.labels.boxes import box_class
from occdata.labels.fidelity import Fidelity
from occdata.labels.score import score_tree
from occdata.nuscenes import load_nuscenes
from occdata.nuscenes.annotations import load_annotations

REPO = Path(__file__).resolve().parents[1]
# One scene of 6 keyframes (5 x 9 sweeps between them) with moving cars, pedestrians and others.
WORLD = {"scenes": 1, "samples": 6, "seed": 11, "width": 320, "height": 180}


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from occdata.synth import SynthConfig, synthesize

    return synthesize(SynthConfig(out=tmp_path_factory.mktemp("labels") / "world", progress=False, **WORLD))


@pytest.fixture(scope="module")
def generated(world: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The world labelled four ways: boxes + sweeps, the same without boxes (control), keyframes only,
    boxes + sweeps + densify."""
    base = tmp_path_factory.mktemp("gen")
    out = {}
    for name, opts in {"ours": LabelOptions(all_sweeps=True),
                       "control": LabelOptions(all_sweeps=True, use_boxes=False),
                       "keyframes": LabelOptions(),
                       "dense": LabelOptions(all_sweeps=True, densify=True)}.items():
        out[name] = base / name
        generate_labels(LabelsConfig(root=world, out=out[name], options=opts, progress=False))
    return out


def _score(world: Path, gen: Path) -> tuple[Fidelity, float, int]:
    t = score_tree(world, gen, world / "gts")
    return t.voxels, t.moving_fraction, t.moving_total


def test_fidelity_targets(world: Path, generated: dict[str, Path]) -> None:
    ours, inside, moved = _score(world, generated["ours"])
    control, inside_control, moved_control = _score(world, generated["control"])
    print(f"\nours: precision {ours.precision:.3f} recall {ours.recall:.3f} semantic {ours.semantic_agreement:.3f} "
          f"moving inside {inside:.3f} ({moved} voxels)\ncontrol: precision {control.precision:.3f} recall "
          f"{control.recall:.3f} moving inside {inside_control:.3f} ({moved_control} voxels)")
    assert ours.precision >= 0.95
    assert ours.recall >= 0.80
    assert ours.semantic_agreement >= 0.95
    assert moved > 100, "the world must have moving objects for this test to mean anything"
    assert inside >= 0.95
    assert inside_control < inside - 0.15, "the control must smear clearly more"


def test_sweeps_add_recall(world: Path, generated: dict[str, Path]) -> None:
    keyframes, _, _ = _score(world, generated["keyframes"])
    ours, _, _ = _score(world, generated["ours"])
    assert ours.recall > keyframes.recall + 0.02


def test_densify_raises_recall_keeps_precision(world: Path, generated: dict[str, Path]) -> None:
    """--densify fills insides and holes: the camera-visible truth it recovers rises clearly (what
    `occdata eval` scores), the visible surface too, in every band, and precision stays above 0.95."""
    ours, dense = score_tree(world, generated["ours"], world / "gts"), score_tree(world, generated["dense"],
                                                                                   world / "gts")
    print(f"\nours: precision {ours.voxels.precision:.3f} visible {ours.voxels.visible_recall:.3f} visible surface "
          f"{ours.voxels.visible_surface_recall:.3f}\ndense: precision {dense.voxels.precision:.3f} visible "
          f"{dense.voxels.visible_recall:.3f} visible surface {dense.voxels.visible_surface_recall:.3f}")
    assert dense.voxels.precision >= 0.95
    assert dense.voxels.visible_recall > ours.voxels.visible_recall + 0.1
    for before, after in zip(ours.bands, dense.bands, strict=True):
        assert after.visible_surface_recall >= before.visible_surface_recall
        assert after.visible_recall > before.visible_recall
    assert dense.moving_fraction >= 0.95
    manifest = json.loads((generated["dense"] / "labels.json").read_text())
    assert manifest["options"]["densify"] is True
    with pytest.raises(OccDataError, match="other settings"):
        generate_labels(LabelsConfig(root=world, out=generated["dense"], options=LabelOptions(all_sweeps=True),
                                     resume=True, progress=False))


def test_layout_manifest_and_build_reads_it(world: Path, generated: dict[str, Path], tmp_path: Path) -> None:
    from occdata.store.build import BuildConfig, build_store

    ds = load_nuscenes(world, None)
    gen = generated["ours"]
    for s in ds.samples:
        with np.load(gen / s.scene_name / s.token / "labels.npz", allow_pickle=False) as z:
            assert sorted(z.files) == ["mask_camera", "mask_lidar", "semantics"]
            for k in z.files:
                assert z[k].dtype == np.uint8 and z[k].shape == (200, 200, 16)
            assert (z["mask_camera"] <= z["mask_lidar"]).all()
    manifest = json.loads((gen / "labels.json").read_text())
    assert manifest["lidarseg"] is True and manifest["options"]["all_sweeps"] is True
    assert manifest["totals"]["keyframes"] == len(ds.samples)
    report = build_store(BuildConfig(root=world, out=tmp_path / "gen.zarr", gts=gen, labels_required=True,
                                     progress=False))
    assert report.n_labelled == len(ds.samples)


def test_same_input_same_bytes_and_resume(world: Path, generated: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "again"
    generate_labels(LabelsConfig(root=world, out=out, options=LabelOptions(), progress=False))
    ref = generated["keyframes"]
    files = sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    for rel in files:
        assert (ref / rel).read_bytes() == (out / rel).read_bytes(), rel
    with pytest.raises(OccDataError, match="--resume"):
        generate_labels(LabelsConfig(root=world, out=out, options=LabelOptions(), progress=False))
    report = generate_labels(LabelsConfig(root=world, out=out, options=LabelOptions(), resume=True, progress=False))
    assert report.scenes_done == 0 and report.scenes_skipped == 1
    with pytest.raises(OccDataError, match="other settings"):
        generate_labels(LabelsConfig(root=world, out=out, options=LabelOptions(all_sweeps=True), resume=True,
                                     progress=False))
    # A record of algorithm version 1 (its option still named `lidar_sweeps`) is not continued: one line.
    for path in (out / ".scenes").glob("*.json"):
        record = json.loads(path.read_text())
        record["settings"]["algorithm_version"] = 1
        record["settings"]["options"]["lidar_sweeps"] = record["settings"]["options"].pop("all_sweeps")
        path.write_text(json.dumps(record))
    with pytest.raises(OccDataError, match="was written with other settings"):
        generate_labels(LabelsConfig(root=world, out=out, options=LabelOptions(), resume=True, progress=False))


def _copy_tables(world: Path, dst: Path) -> Path:
    """The world's tree with its tables copied (editable) and everything else linked."""
    dst.mkdir()
    for p in world.iterdir():
        if p.name != "v1.0-mini":
            (dst / p.name).symlink_to(p)
    shutil.copytree(world / "v1.0-mini", dst / "v1.0-mini")
    return dst


def test_without_lidarseg_static_class_is_stated(world: Path, tmp_path: Path) -> None:
    root = _copy_tables(world, tmp_path / "noseg")
    (root / "v1.0-mini" / "lidarseg.json").unlink()
    out = tmp_path / "gen"
    generate_labels(LabelsConfig(root=root, out=out, options=LabelOptions(static_class=15), progress=False))
    manifest = json.loads((out / "labels.json").read_text())
    assert manifest["lidarseg"] is False
    assert "15 (manmade)" in manifest["classes"] and "not what it is" in manifest["classes"]
    ds = load_nuscenes(root, None)
    ann = load_annotations(root, ds.version)
    tok = ds.samples[0].token
    with np.load(out / ds.samples[0].scene_name / tok / "labels.npz", allow_pickle=False) as z:
        sem = z["semantics"]
    present = set(np.unique(sem).tolist())
    box_classes = {box_class(b) for b in ann.boxes_by_sample[tok]}
    # The ground from geometry takes class 11 (driveable_surface, the default stand-in, stated too).
    assert present <= box_classes | {11, 15, 17}
    assert {11, 15} <= present and present & box_classes
    assert "11 (driveable_surface)" in manifest["classes"] and "flat ground" in manifest["classes"]


def test_bad_inputs_are_one_line(world: Path, tmp_path: Path) -> None:
    root = _copy_tables(world, tmp_path / "bad")
    seg = json.loads((root / "v1.0-mini" / "lidarseg.json").read_text())
    short = tmp_path / "short.bin"
    short.write_bytes(b"\x01" * 10)
    seg[0]["filename"] = os.path.relpath(short, root)
    (root / "v1.0-mini" / "lidarseg.json").write_text(json.dumps(seg))
    r = subprocess.run([sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(root), "--out",
                        str(tmp_path / "o"), "--no-progress"], capture_output=True, text=True, cwd=REPO)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "short.bin" in r.stderr


def test_broken_box_track_is_one_line(world: Path, tmp_path: Path) -> None:
    root = _copy_tables(world, tmp_path / "track")
    path = root / "v1.0-mini" / "sample_annotation.json"
    rows = json.loads(path.read_text())
    row = next(r for r in rows if r["next"])
    row["next"] = "f" * 32
    path.write_text(json.dumps(rows))
    r = subprocess.run([sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(root), "--out",
                        str(tmp_path / "o"), "--no-progress"], capture_output=True, text=True, cwd=REPO)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "f" * 32 in r.stderr or row["token"] in r.stderr


def test_missing_sweep_is_one_line(world: Path, tmp_path: Path) -> None:
    root = tmp_path / "nosweep"
    root.mkdir()
    for p in world.iterdir():
        if p.name != "sweeps":
            (root / p.name).symlink_to(p)
    r = subprocess.run([sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(root), "--out",
                        str(tmp_path / "o"), "--all-sweeps", "--no-progress"], capture_output=True, text=True,
                       cwd=REPO)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "sweeps/LIDAR_TOP" in r.stderr


@pytest.mark.slow
def test_kill_leaves_no_half_file_and_resume_completes(tmp_path: Path) -> None:
    from occdata.synth import SynthConfig, synthesize

    world = synthesize(SynthConfig(out=tmp_path / "w", scenes=3, samples=3, seed=4, width=160, height=90,
                                   progress=False))
    cmd = [sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(world), "--no-progress"]
    subprocess.run([*cmd, "--out", str(tmp_path / "ref")], check=True, cwd=REPO)
    proc = subprocess.Popen([*cmd, "--out", str(tmp_path / "o")], cwd=REPO)
    deadline = time.time() + 300
    while not list((tmp_path / "o" / ".scenes").glob("*.json")) and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    r = subprocess.run([*cmd, "--out", str(tmp_path / "o"), "--resume"], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    ref = tmp_path / "ref"
    got = sorted(p.relative_to(tmp_path / "o") for p in (tmp_path / "o").rglob("*") if p.is_file())
    assert got == sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file())
    for rel in got:
        assert (ref / rel).read_bytes() == (tmp_path / "o" / rel).read_bytes(), rel


def test_build_then_train_on_generated_labels(world: Path, generated: dict[str, Path], tmp_path: Path) -> None:
    """`occdata build --gts <generated>` then `fastocc train` end to end (a tiny run on the CPU)."""
    store = tmp_path / "gen.zarr"
    cli = [sys.executable, "-m"]
    subprocess.run([*cli, "cli.occdata_cli", "build", "--root", str(world), "--gts", str(generated["ours"]),
                    "--out", str(store), "--no-progress"], check=True, cwd=REPO, capture_output=True)
    cfg = tmp_path / "tiny.toml"
    cfg.write_text('input_hw = [64, 176]\nepochs = 1\nworkers = 0\nthreads = 1\nval_every = 0\n'
                   'limit_train_samples = 2\nlr_scaling = "none"\n')
    r = subprocess.run([*cli, "cli.fastocc_cli", "train", "--config", str(cfg), "--store", str(store), "--out",
                        str(tmp_path / "run"), "--batch-size", "1", "--no-progress"], cwd=REPO, capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "run" / "last.pt").is_file()
    assert "done:" in r.stdout


def test_parked_instances_are_held_where_annotation_stops() -> None:
    """Hand-made tracks: a parked car annotated at keyframes 0-1 of 4 is drawn at keyframes 2-3 with
    its keyframe-1 box; a car that drives 5 m is not held; hold_static 0 holds nothing."""
    from occdata.labels.boxes import held_static
    from occdata.nuscenes.annotations import BoxRecord

    def box(tok: str, inst: str, x: float) -> BoxRecord:
        return BoxRecord(tok, inst, "s", "vehicle.car", np.array([x, 0.0, 1.0]), np.array([2.0, 4.0, 1.5]),
                         np.array([1.0, 0, 0, 0]), 0, 10)

    frames = [(box("a0", "park", 0.0), box("m0", "move", 10.0)), (box("a1", "park", 0.05), box("m1", "move", 15.0)),
              (), ()]
    held = held_static(frames, 1.0)
    assert [[b.token for b in h] for h in held] == [[], [], ["a1"], ["a1"]]
    assert held_static(frames, 0.0) == [(), (), (), ()]


def test_two_dask_workers_write_the_same_bytes(synth_root: Path, tmp_path: Path) -> None:
    """Scenes as Dask tasks (a 2-process LocalCluster) give the files of the in-process run."""
    from occdata.runtime.cluster import ClusterConfig

    cfg = {"root": synth_root, "options": LabelOptions(), "progress": False}
    generate_labels(LabelsConfig(out=tmp_path / "one", **cfg))
    report = generate_labels(LabelsConfig(out=tmp_path / "two", cluster=ClusterConfig(workers=2), **cfg))
    assert report.scenes_done == 2
    one = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*") if p.is_file())
    assert one == sorted(p.relative_to(tmp_path / "two") for p in (tmp_path / "two").rglob("*") if p.is_file())
    for rel in one:
        assert (tmp_path / "one" / rel).read_bytes() == (tmp_path / "two" / rel).read_bytes(), rel


def _gated_copy(world: Path, dst: Path) -> tuple[Path, Path]:
    """`world` as a tree of symlinks in which one LiDAR sweep in the middle of the scene is a FIFO:
    a run that reaches it blocks until the test writes the file, so the test knows the run is
    mid-scene. Returns (the FIFO, the real file it stands for)."""
    shutil.copytree(world, dst, symlinks=False, copy_function=os.symlink)
    sweeps = sorted((dst / "sweeps" / "LIDAR_TOP").iterdir())
    gate = sweeps[len(sweeps) // 2]
    real = gate.resolve()
    gate.unlink()
    os.mkfifo(gate)
    return gate, real


def _open_when_read(fifo: Path, timeout: float) -> int:
    """Open `fifo` for writing once a reader has it open (ENXIO until then); fail after `timeout`."""
    t_end = time.time() + timeout
    while True:
        try:
            return os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:
            if time.time() > t_end:
                raise AssertionError(f"the run never read {fifo.name}") from None
            time.sleep(0.05)


def test_sigterm_stops_mid_scene_and_resume_completes(world: Path, generated: dict[str, Path],
                                                    tmp_path: Path) -> None:
    """SIGTERM in the middle of a scene (in-process run): exit 143 at the next frame, one line, no record
    and no half-written file for that scene; --resume then writes the files of an uninterrupted run."""
    root, out = tmp_path / "world", tmp_path / "o"
    gate, real = _gated_copy(world, root)
    cmd = [sys.executable, "-m", "cli.occdata_cli", "labels", "--root", str(root), "--out", str(out),
           "--all-sweeps", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=REPO, stderr=subprocess.PIPE, text=True)
    fd = _open_when_read(gate, timeout=120)  # the run is reading a sweep in the middle of the scene
    proc.send_signal(signal.SIGTERM)
    os.set_blocking(fd, True)
    os.write(fd, real.read_bytes())  # let the read finish; the run stops at the next frame
    os.close(fd)
    _, err = proc.communicate(timeout=120)  # a hang guard, not a speed limit
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "--resume" in err
    assert not list((out / ".scenes").glob("*.json"))
    gate.unlink()
    os.symlink(real, gate)
    r = subprocess.run([*cmd, "--resume"], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    ref = generated["ours"]
    for p in ref.rglob("labels.npz"):
        assert (out / p.relative_to(ref)).read_bytes() == p.read_bytes()
    assert not list(out.rglob(f"*{'.tmp'}"))
