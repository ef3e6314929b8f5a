"""Epoch plans: which samples each (rank, worker) yields, in what grouping, for a given (seed, epoch).

Shuffled order: the loadable samples are cut into chunk-aligned units (runs inside one store block),
the units are shuffled and dealt greedily (fewest samples first) to the R x W (rank, worker) slots.
Each slot then reads its units in order and shuffles samples through a buffer (dataset.py).

Scene-sequential order: every scene is cut into segments of consecutive loadable samples (at most
`segment_len`) and the segments are shuffled. Each rank then owns B lanes (B = batch size); batch t
of a rank holds lane j's t-th sample in slot j, so each slot walks its lane in time order. Worker w of
W produces the rank's batches t = w, w + W, ... which a DataLoader (in-order round robin over workers)
returns in t order. `seq_start` is True at a segment's first sample and at a lane's first sample.
Two ways to make the lanes:

- exactly once (`equal_lanes=False`, evaluation): whole segments are dealt greedily to ranks, then to
  lanes. Lanes differ in length, so ranks differ in batch count and the tail batches shrink. Lanes are
  sorted longest first: the live lanes are always slots 0..k-1, a lane never changes slot, and a
  shrinking batch loses its last rows (TemporalFusion keeps the first rows of its queue).
- equal steps (`equal_lanes=True`, training): the shuffled segments are laid end to end into one
  stream of n samples and cut into R x B lanes of the common length L = n // (R B); rank r takes lanes
  rB .. rB + B - 1. Every rank runs exactly L full batches (the same number of optimizer steps, so DDP
  never waits at an epoch end), for any number of workers. Cost: the last n mod (R B) < R B samples of
  the epoch's stream are not seen that epoch (a different tail each epoch), and up to R B - 1 segments
  are cut in two by a lane boundary (the second part starts with an empty queue). We cut rather than
  pad: padding frames would cost forwards that carry no loss and a loss mask through DDP. Measured
  costs: docs/data.md.

The shuffled plan and the exactly-once sequential plan yield every loadable sample exactly once across
all ranks x workers. With `pad=True` (shuffled order) every slot is topped up to the largest slot's
count by repeating its own first samples, so all ranks see the same number of samples (DDP needs equal
step counts); those repeats are the only duplicates. Plans depend only on (seed, epoch, ranks, workers, batch size), so
every rank computes every rank's plan without communication.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occdata.errors import OccDataError

__all__ = ["Slot", "sequential_batches", "shuffle_units"]


@dataclass(frozen=True)
class Slot:
    rank: int = 0
    world_size: int = 1
    worker: int = 0
    num_workers: int = 1

    @property
    def id(self) -> int:
        return self.rank * self.num_workers + self.worker

    @property
    def count(self) -> int:
        return self.world_size * self.num_workers


def _deal(sizes: list[int], n_bins: int) -> list[list[int]]:
    """Greedy: item k (in the given order) goes to the bin with the fewest items so far (lowest id on ties)."""
    bins: list[list[int]] = [[] for _ in range(n_bins)]
    load = np.zeros(n_bins, dtype=np.int64)
    for k, size in enumerate(sizes):
        b = int(np.argmin(load))
        bins[b].append(k)
        load[b] += size
    return bins


def shuffle_units(indices: np.ndarray, block: int, slot: Slot, seed: int, epoch: int, pad: bool = False,
                  shuffle: bool = True) -> list[np.ndarray]:
    """Units (arrays of store indices inside one block, ascending) for this slot, in read order."""
    indices = np.asarray(indices, dtype=np.int64)
    # Small stores: finer units so that every slot gets work; large ones read whole blocks.
    unit = max(1, min(block, -(-len(indices) // (4 * slot.count))))
    keys = (indices // block) * block + (indices % block) // unit
    cuts = np.flatnonzero(np.diff(keys)) + 1
    units = np.split(indices, cuts) if len(indices) else []
    order = np.random.default_rng([seed, epoch]).permutation(len(units)) if shuffle else np.arange(len(units))
    units = [units[k] for k in order]
    bins = _deal([len(u) for u in units], slot.count)
    mine = [units[k] for k in bins[slot.id]]
    if pad:
        target = max(sum(len(units[k]) for k in b) for b in bins)
        have = sum(len(u) for u in mine)
        source = np.concatenate(mine) if mine else np.concatenate(units)
        if target > have:
            extra = np.resize(source, target - have)
            mine = mine + [np.sort(extra[j: j + block]) for j in range(0, len(extra), block)]
    return mine


def _segments(indices: np.ndarray, scene_index: np.ndarray, segment_len: int | None) -> list[np.ndarray]:
    indices = np.asarray(indices, dtype=np.int64)
    if not len(indices):
        return []
    # A new segment starts at a scene change or a gap (a sample that is not loadable).
    brk = (np.diff(indices) != 1) | (np.diff(scene_index[indices]) != 0)
    segs = np.split(indices, np.flatnonzero(brk) + 1)
    if segment_len:
        segs = [s[j: j + segment_len] for s in segs for j in range(0, len(s), segment_len)]
    return segs


def _shuffled_segments(indices: np.ndarray, scene_index: np.ndarray, seed: int, epoch: int,
                       segment_len: int | None, shuffle: bool) -> list[np.ndarray]:
    segs = _segments(indices, scene_index, segment_len)
    order = np.random.default_rng([seed, epoch, 1]).permutation(len(segs)) if shuffle else np.arange(len(segs))
    return [segs[k] for k in order]


def _dealt_lanes(segs: list[np.ndarray], slot: Slot, batch_size: int) -> list[list[tuple[int, bool]]]:
    """Exactly once: whole segments dealt to ranks, then to lanes; lanes sorted longest first."""
    rank_bins = _deal([len(s) for s in segs], slot.world_size)
    mine = [segs[k] for k in rank_bins[slot.rank]]
    lane_bins = _deal([len(s) for s in mine], batch_size)
    lanes = [[(int(x), j == 0) for k in b for j, x in enumerate(mine[k])] for b in lane_bins]
    # Longest first (stable): the live lanes are always slots 0..k-1, so a lane never changes slot and
    # a shrinking tail batch drops its LAST rows (TemporalFusion keeps the first rows of its queue).
    return sorted(lanes, key=len, reverse=True)


def _equal_lanes(segs: list[np.ndarray], slot: Slot, batch_size: int) -> list[list[tuple[int, bool]]]:
    """Equal steps: the segment stream cut into ranks x batch_size lanes of one length L = n // (R B)."""
    stream = [(int(x), j == 0) for s in segs for j, x in enumerate(s)]
    n_lanes = slot.world_size * batch_size
    length = len(stream) // n_lanes
    if stream and not length:
        raise OccDataError(f"scene-sequential order: {len(stream)} samples cannot fill {slot.world_size} process(es) "
                           f"x batch {batch_size} lanes of at least one sample; use fewer processes or a smaller "
                           "batch")
    lanes = []
    for k in range(slot.rank * batch_size, (slot.rank + 1) * batch_size):
        lane = stream[k * length: (k + 1) * length]
        if lane:  # a lane cut inside a segment starts a new sequence (empty queue)
            lane[0] = (lane[0][0], True)
        lanes.append(lane)
    return lanes


def sequential_batches(indices: np.ndarray, scene_index: np.ndarray, slot: Slot, batch_size: int, seed: int,
                       epoch: int, segment_len: int | None = None, shuffle: bool = True,
                       equal_lanes: bool = False) -> list[list[tuple[int, bool]]]:
    """This worker's batches: lists of (store index, seq_start), time-ordered per slot (module doc).

    equal_lanes=False: every sample exactly once, ranks may differ in batch count (evaluation).
    equal_lanes=True: every rank gets exactly n // (ranks x batch_size) full batches (training).
    """
    segs = _shuffled_segments(indices, scene_index, seed, epoch, segment_len, shuffle)
    lanes = (_equal_lanes if equal_lanes else _dealt_lanes)(segs, slot, batch_size)
    n_steps = max((len(lane) for lane in lanes), default=0)
    batches = [[lane[t] for lane in lanes if t < len(lane)] for t in range(n_steps)]
    return batches[slot.worker:: slot.num_workers]
