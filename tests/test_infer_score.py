"""fastocc.infer.score: a checkpoint scored through `score_checkpoint` gets the figures `evaluate` gives
the same weights, plus the checkpoint's meta; noise images are seeded (repeated scores agree)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fastocc.checkpoint import save_checkpoint
from fastocc.infer import PredictConfig, evaluate
from fastocc.infer.score import report_metrics, score_checkpoint
from fastocc.model import FastOcc, preset

CFG = preset("nano", input_hw=(64, 176))  # small input: the test is about plumbing, not the network


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, FastOcc]:
    torch.manual_seed(0)
    model = FastOcc(CFG).eval()
    path = save_checkpoint(tmp_path_factory.mktemp("ckpt") / "c.pt", CFG, model.state_dict(),
                           meta={"opt_steps": 7, "samples_seen": 14})
    return path, model


def test_score_checkpoint_matches_evaluate(synth_store: Path, checkpoint: tuple[Path, FastOcc]) -> None:
    path, model = checkpoint
    s = score_checkpoint(path, synth_store, "val", rayiou=False)
    ref = report_metrics(evaluate(model, CFG, PredictConfig(store=synth_store, split="val"), rayiou=False,
                                  progress=False))
    assert s["miou"] == ref["miou"] and s["geo_iou"] == ref["geo_iou"] and s["samples"] == ref["samples"] > 0
    assert s["rayiou"] is None and ref["rayiou"] is None
    assert (s["checkpoint"], s["opt_steps"], s["samples_seen"], s["ema"]) == ("c.pt", 7, 14, False)
    assert s["frames_per_s"] > 0 and s["infer_seconds"] > 0


def test_score_checkpoint_noise_images_repeat(synth_store: Path, checkpoint: tuple[Path, FastOcc]) -> None:
    path, _ = checkpoint
    a = score_checkpoint(path, synth_store, "val", rayiou=False, noise_images=True)
    b = score_checkpoint(path, synth_store, "val", rayiou=False, noise_images=True)
    assert (a["miou"], a["geo_iou"]) == (b["miou"], b["geo_iou"])
