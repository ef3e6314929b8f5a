"""predict_split: every sample of the split once, probabilities, exact BEV-flip TTA."""

from __future__ import annotations

from pathlib import Path

import torch

from fastocc.infer import PredictConfig, bev_flip_variants, predict_split
from fastocc.model import FastOcc, preset, synthetic_inputs
from occdata.store.reader import open_store


def test_predict_split_covers_split_once(synth_store: Path) -> None:
    torch.manual_seed(0)
    cfg = preset("nano")
    model = FastOcc(cfg)
    reader = open_store(synth_store)
    split_names = list(reader.attrs["splits"])
    val = set(int(i) for i in (reader.small("sample/split") == split_names.index("val")).nonzero()[0])
    seen = []
    for batch, probs in predict_split(model, cfg, PredictConfig(store=synth_store, split="val", batch_size=2)):
        assert probs.shape == (len(batch), 18, 200, 200, 16)
        torch.testing.assert_close(probs.sum(1), torch.ones(len(batch), 200, 200, 16))
        seen += batch.sample_index.tolist()
    assert sorted(seen) == sorted(val) and len(val) > 0


class _WorldProbe(torch.nn.Module):
    """Stands in for a network that predicts a fixed world: class 4 where key-ego x > 5 m and y < -3 m,
    free elsewhere, emitted on the augmented grid of `bev_aug` (as the real network's output is)."""

    def forward(self, inp):  # noqa: ANN001, ANN201
        from types import SimpleNamespace

        from occdata.constants import GRID

        c = torch.from_numpy(GRID.voxel_centers()).double()  # augmented-frame voxel centres
        M = inp.bev_aug[0].double()
        world = c @ torch.linalg.inv(M)[:3, :3].T
        hit = (world[..., 0] > 5) & (world[..., 1] < -3)
        logits = torch.zeros(1, 18, *GRID.shape)
        logits[0, 17] = 10.0
        logits[0, 4][hit] = 20.0
        return SimpleNamespace(voxel_logits=logits)


def test_tta_unflips_exactly() -> None:
    """Each flip variant, un-flipped, gives the same world back (and the flip is in M)."""
    from fastocc.infer.predict import _unflip

    inputs = synthetic_inputs(1, (128, 352))
    variants = bev_flip_variants(inputs)
    assert [v[0] for v in variants] == [(False, False), (True, False), (False, True), (True, True)]
    probe = _WorldProbe()
    plain = torch.softmax(probe(inputs).voxel_logits, 1)
    assert plain[0, 4].sum() > 1000
    for (fx, fy), inp in variants:
        expect = torch.diag(torch.tensor([-1.0 if fx else 1.0, -1.0 if fy else 1.0, 1.0, 1.0]))
        torch.testing.assert_close(inp.bev_aug[0], expect)
        out = torch.softmax(probe(inp).voxel_logits, 1)
        if fx or fy:
            assert not torch.equal(out, plain)
        torch.testing.assert_close(_unflip(out, fx, fy), plain)
