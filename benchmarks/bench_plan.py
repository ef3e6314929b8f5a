"""What the scene-sequential training plan costs in samples (docs/data.md).

Research: the figures behind the choice of the equal-lanes plan (docs/data.md). Indexed in
benchmarks/README.md.

    python -m benchmarks.bench_plan

6 scenes of unequal length (40, 35, 30, 25, 20, 12 samples), 2 and 3 ranks, batch 1 and 2 per rank,
20 epochs. Compares the equal-lanes plan (training) with cutting or padding the exactly-once plan.
"""

from __future__ import annotations

import numpy as np

from fastocc.data.order import Slot, sequential_batches

__all__: list[str] = []

LENGTHS = [40, 35, 30, 25, 20, 12]


def main() -> None:
    scene_index = np.repeat(np.arange(len(LENGTHS)), LENGTHS)
    idx = np.arange(len(scene_index))
    n = len(idx)
    print(f"scenes {LENGTHS}: {n} samples; percentages of n, mean over 20 epochs")
    print("ranks batch | steps/rank  dropped  sequence starts | exactly-once plan: cut to common  padded")
    for ranks in (2, 3):
        for batch in (1, 2):
            kept, starts, cut_kept, padded = [], [], [], []
            for epoch in range(20):
                plans = [sequential_batches(idx, scene_index, Slot(r, ranks), batch, 0, epoch, equal_lanes=True)
                         for r in range(ranks)]
                kept.append(sum(len(b) for p in plans for b in p))
                starts.append(sum(s for p in plans for b in p for _, s in b))
                once = [sequential_batches(idx, scene_index, Slot(r, ranks), batch, 0, epoch) for r in range(ranks)]
                common, most = min(map(len, once)), max(map(len, once))
                cut_kept.append(sum(len(b) for p in once for b in p[:common]))
                padded.append(ranks * batch * most - n)
            print(f"{ranks:5d} {batch:5d} | {len(plans[0]):10d} {100 * (1 - np.mean(kept) / n):7.1f}% "
                  f"{np.mean(starts):16.1f} | {100 * (1 - np.mean(cut_kept) / n):26.1f}% "
                  f"{100 * np.mean(padded) / n:6.1f}%")


if __name__ == "__main__":
    main()
