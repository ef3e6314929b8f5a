"""Does a recurrent model use its state? Score its checkpoints with the state zeroed at every frame.

Research: one diagnostic of the recurrent fusion (docs/ablations.md, -4.3 mIoU without its state).
Indexed in benchmarks/README.md.

    cd <ablation folder> && python -m benchmarks.ablations_nohistory --row hist16rec --json out.json

Each checkpoint `RUNS/<row>-s<seed>/last.pt` is scored on the val split (`fastocc.infer.score`, mIoU
with the camera mask, RayIoU, geometry IoU) as if every frame started a sequence: the recurrent
fusion's state is zero each time, so the network sees the current frame only. Compare with the row's
own scores in docs/results/ablations.json (the reading in docs/ablations.md, "History").
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from benchmarks.common import write_json

__all__ = ["no_history", "score_without_history"]


@contextlib.contextmanager
def no_history() -> Iterator[None]:
    """Within: every `RecurrentFusion` frame is a sequence start (its state zero)."""
    from fastocc.model.recurrent import RecurrentFusion

    begin = RecurrentFusion._begin

    def fresh(self: RecurrentFusion, bev: torch.Tensor, pose: torch.Tensor, aug: torch.Tensor,
              start: torch.Tensor | None) -> dict[str, torch.Tensor]:
        return begin(self, bev, pose, aug, torch.ones(bev.shape[0], dtype=torch.bool, device=bev.device))

    RecurrentFusion._begin = fresh  # type: ignore[method-assign]
    try:
        yield
    finally:
        RecurrentFusion._begin = begin  # type: ignore[method-assign]


def score_without_history(runs: Path, row: str, seeds: tuple[int, ...], store: str) -> dict[str, Any]:
    from fastocc.infer.score import score_checkpoint

    out: dict[str, Any] = {}
    with no_history():
        for s in seeds:
            r = score_checkpoint(runs / f"{row}-s{s}" / "last.pt", store, "val", rayiou=True, workers=0)
            out[f"{row}-s{s}"] = {k: r[k] for k in ("miou", "rayiou", "geo_iou")}
            print(f"{row}-s{s}: {out[f'{row}-s{s}']}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--row", default="hist16rec")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--runs-dir", type=Path, default=Path("runs"))
    ap.add_argument("--store", default="w8v.zarr")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    res = score_without_history(args.runs_dir, args.row, tuple(args.seeds), args.store)
    if args.json:
        write_json(res, args.json)


if __name__ == "__main__":
    main()
