"""Epoch plans: which samples each (rank, worker) yields, in what grouping, for a given (seed, epoch).

Shuffled order: the loadable samples are cut into chunk-aligned units (runs inside one store block),
the units are shuffled and dealt greedily (fewest samples first) to the R x W (rank, worker) slots.
Each slot then reads its units in order and shuffles samples through a buffer (dataset.py).

Scene-sequential order: every scene is cut into segments of consecutive loadable samples (at most
`segment_len`); segments are shuffled and dealt greedily to ranks; within a rank they are dealt to
B lanes (B = batch size). Batch t of a rank holds lane j's t-th sample in slot j, so each slot walks
whole segments in time order; worker w of W produces the rank's batches t = w, w + W, ... which a
DataLoader (in-order round robin over workers) returns in t order. `seq_start` is True at a
segment's first sample and wherever a sample's slot differs from its lane's previous slot (lanes
that run out shrink the tail batches).

Both plans yield every loadable sample exactly once across all ranks x workers. With
`pad=True` (shuffled order) every slot is topped up to the largest slot's count by repeating its own
first samples, so all ranks see the same number of samples (DDP needs equal step counts); those
repeats are the only duplicates. Plans depend only on (seed, epoch, ranks, workers, batch size).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def sequential_batches(indices: np.ndarray, scene_index: np.ndarray, slot: Slot, batch_size: int, seed: int,
                       epoch: int, segment_len: int | None = None, shuffle: bool = True
                       ) -> list[list[tuple[int, bool]]]:
    """This worker's batches: lists of (store index, seq_start), time-ordered per slot (module doc)."""
    segs = _segments(indices, scene_index, segment_len)
    order = np.random.default_rng([seed, epoch, 1]).permutation(len(segs)) if shuffle else np.arange(len(segs))
    segs = [segs[k] for k in order]
    rank_bins = _deal([len(s) for s in segs], slot.world_size)
    mine = [segs[k] for k in rank_bins[slot.rank]]
    lane_bins = _deal([len(s) for s in mine], batch_size)
    lanes: list[list[tuple[int, bool]]] = []
    for b in lane_bins:
        lane = []
        for k in b:
            lane += [(int(x), j == 0) for j, x in enumerate(mine[k])]
        lanes.append(lane)
    n_steps = max((len(lane) for lane in lanes), default=0)
    batches: list[list[tuple[int, bool]]] = []
    prev_slot = [-1] * len(lanes)
    for t in range(n_steps):
        batch = []
        for j, lane in enumerate(lanes):
            if t < len(lane):
                idx, start = lane[t]
                pos = len(batch)
                batch.append((idx, start or pos != prev_slot[j]))
                prev_slot[j] = pos
        batches.append(batch)
    return batches[slot.worker:: slot.num_workers]
