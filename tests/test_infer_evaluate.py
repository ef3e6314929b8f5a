"""evaluate(): an oracle network scores 100, a known confusion scores what we derive by hand, sharded
runs reduce to the single-process numbers, TTA keeps an exact oracle exact."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from fastocc.infer import PredictConfig
from fastocc.infer.evaluate import EvalReport, evaluate, reduce_reports
from fastocc.model import preset
from occdata.constants import FREE_LABEL, NUM_CLASSES
from occdata.errors import OccDataError
from occdata.store.reader import open_store

CAR, TRUCK = 4, 10


class _Oracle(torch.nn.Module):
    """A "network" that knows the world: it recognises its sample by the ego pose in the inputs, reads
    that sample's ground truth from the store and emits it as one-hot logits on the AUGMENTED grid
    (flipped as `bev_aug` says), exactly as a perfect FastOcc would. `relabel` maps classes (a known
    confusion)."""

    seen: list[tuple[int, bool, bool]] = []

    def __init__(self, store: Path, relabel: dict[int, int] | None = None) -> None:
        super().__init__()
        self.reader = open_store(store)
        self.poses = self.reader.small("pose/T_global_from_keyego")
        self.lut = np.arange(256, dtype=np.uint8)
        for a, b in (relabel or {}).items():
            self.lut[a] = b
        type(self).seen = []  # class-level: TTA runs deep copies of the module, all record here

    def clear_caches(self) -> None:  # the temporal-queue reset that predict_split calls
        pass

    def forward(self, inp):  # noqa: ANN001, ANN201
        out = []
        for b in range(inp.batch_size):
            T = inp.T_global_from_keyego[b].double().numpy()
            idx = int(np.argmin(np.abs(self.poses - T).reshape(len(self.poses), -1).max(1)))
            assert np.abs(self.poses[idx] - T).max() < 1e-2
            sem = self.lut[self.reader.sample_arrays(idx, ("labels/semantics",))["labels/semantics"]]
            M = inp.bev_aug[b].numpy()
            assert np.allclose(np.abs(np.diag(M)), 1) and np.allclose(M - np.diag(np.diag(M)), 0)
            type(self).seen.append((idx, bool(M[0, 0] < 0), bool(M[1, 1] < 0)))
            if M[0, 0] < 0:
                sem = sem[::-1]
            if M[1, 1] < 0:
                sem = sem[:, ::-1]
            onehot = torch.nn.functional.one_hot(torch.from_numpy(sem.astype(np.int64)), NUM_CLASSES)
            out.append(onehot.permute(3, 0, 1, 2).float() * 20.0)
        return SimpleNamespace(voxel_logits=torch.stack(out))


def _gt_classes(store: Path, split: str | None, mask: str = "camera") -> set[int]:
    """Classes 0..16 present in the ground truth under the mask over the split (read directly)."""
    r = open_store(store)
    names = list(r.attrs["splits"])
    idx = np.arange(r.n_samples) if split is None else np.flatnonzero(r.small("sample/split") == names.index(split))
    present: set[int] = set()
    for i in idx:
        a = r.sample_arrays(int(i), ("labels/semantics", "labels/mask_camera"))
        sem = a["labels/semantics"][a["labels/mask_camera"] > 0] if mask == "camera" else a["labels/semantics"]
        present |= {int(c) for c in np.unique(sem) if c != FREE_LABEL}
    return present


@pytest.mark.parametrize("tta", [False, True])
def test_oracle_scores_100(synth_store: Path, tta: bool) -> None:
    oracle = _Oracle(synth_store)
    rep = evaluate(oracle, preset("nano"), PredictConfig(store=synth_store, split="val", tta=tta), progress=False)
    assert isinstance(rep, EvalReport)
    present = _gt_classes(synth_store, "val")
    assert len(present) >= 3  # the synthetic world has road, cars, buildings, ...
    assert rep.samples == rep.frames == 3 and rep.tta is tta
    assert rep.miou.miou == pytest.approx(1.0)
    iou = rep.miou.per_class_iou
    for c in range(FREE_LABEL):
        assert (iou[c] == pytest.approx(1.0)) if c in present else np.isnan(iou[c])
    assert rep.rayiou is not None and rep.rayiou.rayiou == pytest.approx(1.0)
    assert rep.frames_per_s > 0 and rep.seconds >= rep.infer_seconds > 0
    j = rep.to_json()
    assert j["miou"] == pytest.approx(100.0) and j["n_samples"] == 3 and j["unit"] == "percent"
    flips = [(False, False), (True, False), (False, True), (True, True)] if tta else [(False, False)]
    # every sample seen once per flip variant (and each variant un-flipped back to the truth: 100 above)
    assert sorted(_Oracle.seen) == sorted((i, fx, fy) for i in {s[0] for s in _Oracle.seen} for fx, fy in flips)
    assert len({s[0] for s in _Oracle.seen}) == 3


def test_known_confusion(synth_store: Path) -> None:
    """Every car voxel predicted as truck: car IoU 0; truck IoU 0 (absent from the truth, so only FP)
    or car/(car+truck) share if trucks exist; every other class stays 1.0."""
    present = _gt_classes(synth_store, "val")
    assert CAR in present
    rep = evaluate(_Oracle(synth_store, {CAR: TRUCK}), preset("nano"), PredictConfig(store=synth_store, split="val"),
                   rayiou=False, progress=False)
    assert rep.rayiou is None
    iou = rep.miou.per_class_iou
    assert iou[CAR] == 0.0
    scored = present | {TRUCK}
    if TRUCK not in present:
        assert iou[TRUCK] == 0.0
        expect = (len(scored) - 2) / len(scored)
        assert rep.miou.miou == pytest.approx(expect)
    for c in scored - {CAR, TRUCK}:
        assert iou[c] == pytest.approx(1.0)
    assert rep.miou.geo_iou == pytest.approx(1.0)  # occupied/free is unchanged by a class swap


def test_sharded_reduces_to_single(synth_store: Path) -> None:
    cfg = PredictConfig(store=synth_store, split=None)
    single = evaluate(_Oracle(synth_store, {CAR: TRUCK}), preset("nano"), cfg, progress=False)
    parts = [evaluate(_Oracle(synth_store, {CAR: TRUCK}), preset("nano"), cfg, progress=False, rank=r, world_size=2)
             for r in range(2)]
    assert all(p.samples > 0 for p in parts)  # two scenes: one per rank
    both = reduce_reports(parts)
    assert both.samples == single.samples == 6
    np.testing.assert_array_equal(both.miou_state, single.miou_state)
    np.testing.assert_array_equal(both.rayiou_state, single.rayiou_state)
    assert both.miou.miou == pytest.approx(single.miou.miou)
    assert both.rayiou.rayiou == pytest.approx(single.rayiou.rayiou)


def test_bad_split(synth_store: Path) -> None:
    with pytest.raises(OccDataError, match="unknown split"):
        evaluate(_Oracle(synth_store), preset("nano"), PredictConfig(store=synth_store, split="nope"), progress=False)


def _random_report(seed: int) -> EvalReport:
    from fastocc.infer.evaluate import _report
    from occdata.eval.metrics import MIoUAccumulator, RayIoUAccumulator

    rng = np.random.default_rng(seed)
    miou = MIoUAccumulator.from_state(rng.integers(0, 1000, (18, 18)))
    ray = RayIoUAccumulator.from_state(rng.integers(0, 1000, (5, 17)))
    return _report(miou, ray, samples=3 + seed, frames=4 + seed, seconds=10.0 + seed, infer_seconds=5.0 + seed,
                   tta=False, split="val", mask="camera")


def _ddp_worker(rank: int, world: int, init: str, out: str) -> None:
    import torch.distributed as dist

    from fastocc.infer.evaluate import all_reduce_report

    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    try:
        rep = all_reduce_report(_random_report(rank))
        np.savez(f"{out}_{rank}.npz", miou=rep.miou_state, ray=rep.rayiou_state,
                 scal=np.array([rep.samples, rep.frames, rep.seconds, rep.infer_seconds, rep.miou.miou]))
    finally:
        dist.destroy_process_group()


def test_all_reduce_report_matches_reduce_reports(tmp_path: Path) -> None:
    """Two gloo processes all-reduce their reports: each gets exactly `reduce_reports` of both."""
    import torch.multiprocessing as mp

    out = str(tmp_path / "r")
    mp.spawn(_ddp_worker, args=(2, f"file://{tmp_path / 'rdzv'}", out), nprocs=2, join=True)
    want = reduce_reports([_random_report(0), _random_report(1)])
    assert want.samples == 7 and want.frames == 9 and want.seconds == 11.0 and want.infer_seconds == 6.0
    for rank in range(2):
        with np.load(f"{out}_{rank}.npz") as z:
            np.testing.assert_array_equal(z["miou"], want.miou_state)
            np.testing.assert_array_equal(z["ray"], want.rayiou_state)
            np.testing.assert_allclose(z["scal"], [7, 9, 11.0, 6.0, want.miou.miou])
