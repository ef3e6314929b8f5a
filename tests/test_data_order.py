"""Epoch plans (`fastocc.data.order`): equal step counts on every rank, exactly-once coverage, time order.

Pure functions of (seed, epoch, ranks, workers, batch size): no store needed. The scene layouts have
unequal scene lengths and gaps (samples that did not build), the cases where ranks used to disagree.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fastocc.data.order import Slot, sequential_batches, shuffle_units
from occdata.errors import OccDataError


def _layout(lengths: list[int], gaps: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Loadable indices and scene_index of a store with scenes of `lengths` samples; `gaps` did not build."""
    scene_index = np.repeat(np.arange(len(lengths)), lengths)
    indices = np.setdiff1d(np.arange(len(scene_index)), gaps)
    return indices, scene_index


LAYOUTS = [
    _layout([40, 35, 30, 25, 20, 12]),  # 6 scenes of unequal length (162 samples)
    _layout([7, 3, 11, 1, 5], gaps=(2, 12)),  # short scenes, a 1-sample scene, two gaps
    _layout([9, 9, 9]),
]


def _rank_batches(indices, scene_index, rank, ranks, workers, batch, seed, epoch, equal, segment_len=None):
    """This rank's batches in the order a DataLoader returns them (round robin over its workers)."""
    per_worker = [sequential_batches(indices, scene_index, Slot(rank, ranks, w, workers), batch, seed, epoch,
                                     segment_len, equal_lanes=equal) for w in range(workers)]
    out = []
    for t in range(sum(len(p) for p in per_worker)):
        out.append(per_worker[t % workers][t // workers])
    return out


def _lanes(batches: list[list[tuple[int, bool]]]) -> list[list[tuple[int, bool]]]:
    lanes: dict[int, list[tuple[int, bool]]] = {}
    for b in batches:
        for slot, entry in enumerate(b):
            lanes.setdefault(slot, []).append(entry)
    return list(lanes.values())


def _check_time_order(lane: list[tuple[int, bool]], scene_index: np.ndarray, loadable: set[int],
                      segment_len: int | None) -> None:
    """Independent truth: a slot continues only with the next sample of the same scene; seq_start is
    True exactly where it does not continue (and at the lane start). With segment_len a cut may also
    start a sequence inside a continuous run."""
    assert lane[0][1], "a lane's first sample starts a sequence"
    for (i0, _), (i1, s1) in itertools.pairwise(lane):
        continuous = i1 == i0 + 1 and scene_index[i1] == scene_index[i0] and i1 in loadable
        if not continuous:
            assert s1, (i0, i1)
        elif segment_len is None:
            assert not s1, (i0, i1)


@pytest.mark.parametrize("layout", range(len(LAYOUTS)))
def test_equal_lanes_give_every_rank_the_same_number_of_full_batches(layout: int) -> None:
    indices, scene_index = LAYOUTS[layout]
    loadable = set(indices.tolist())
    n = len(indices)
    for ranks, workers, batch, segment_len, epoch in itertools.product((1, 2, 3, 4), (1, 2, 3), (1, 2, 3),
                                                                       (None, 4), (0, 5)):
        if n < ranks * batch:
            continue
        length = n // (ranks * batch)
        seen: list[int] = []
        for rank in range(ranks):
            batches = _rank_batches(indices, scene_index, rank, ranks, workers, batch, 11, epoch, True, segment_len)
            assert len(batches) == length, (ranks, workers, batch)  # same steps on every rank, any W
            assert all(len(b) == batch for b in batches)  # always full: the temporal queue keeps its rows
            for lane in _lanes(batches):
                _check_time_order(lane, scene_index, loadable, segment_len)
            seen += [i for b in batches for i, _ in b]
        assert len(seen) == len(set(seen)) == ranks * batch * length  # each kept sample once
        assert set(seen) <= loadable and n - len(seen) < ranks * batch  # drops < R x B


def test_equal_lanes_drop_a_different_tail_each_epoch() -> None:
    indices, scene_index = LAYOUTS[0]  # 162 samples on 2 ranks x batch 2: 2 dropped per epoch
    dropped = []
    for epoch in range(4):
        kept = {i for r in range(2) for b in _rank_batches(indices, scene_index, r, 2, 1, 2, 0, epoch, True)
                for i, _ in b}
        dropped.append(frozenset(set(indices.tolist()) - kept))
    assert all(len(d) == 2 for d in dropped) and len(set(dropped)) > 1


@pytest.mark.parametrize("layout", range(len(LAYOUTS)))
def test_exactly_once_lanes_keep_their_slot_and_cover_every_sample(layout: int) -> None:
    indices, scene_index = LAYOUTS[layout]
    loadable = set(indices.tolist())
    for ranks, workers, batch in itertools.product((1, 2, 3), (1, 2), (1, 2, 3)):
        seen: list[int] = []
        for rank in range(ranks):
            batches = _rank_batches(indices, scene_index, rank, ranks, workers, batch, 4, 1, False)
            sizes = [len(b) for b in batches]
            assert sizes == sorted(sizes, reverse=True)  # lanes end from the last slot backwards
            for lane in _lanes(batches):
                _check_time_order(lane, scene_index, loadable, None)
            for i, start in (e for b in batches for e in b):
                # History is never lost: a sequence starts only where the store's scene run starts.
                assert start == (i - 1 not in loadable or scene_index[i - 1] != scene_index[i]), i
            seen += [i for b in batches for i, _ in b]
        assert sorted(seen) == sorted(loadable)  # every sample exactly once


def test_exactly_once_plan_keeps_whole_scenes_on_one_rank() -> None:
    """Evaluation shards by whole scenes, so a sample's history is the same on any number of ranks."""
    indices, scene_index = LAYOUTS[0]
    for ranks in (2, 3):
        owner = {}
        for rank in range(ranks):
            for b in _rank_batches(indices, scene_index, rank, ranks, 1, 1, 0, 0, False):
                for i, _ in b:
                    owner.setdefault(int(scene_index[i]), set()).add(rank)
        assert all(len(r) == 1 for r in owner.values())


def test_equal_lanes_with_too_few_samples_is_a_clear_error() -> None:
    indices, scene_index = _layout([2, 1])
    with pytest.raises(OccDataError, match="3 samples cannot fill 2 process"):
        sequential_batches(indices, scene_index, Slot(0, 2), 2, 0, 0, equal_lanes=True)


@pytest.mark.parametrize("block", [4, 32])
def test_shuffled_pad_gives_every_rank_the_same_number_of_batches(block: int) -> None:
    for n, gaps, ranks, workers, batch in itertools.product((7, 50, 162), ((), (3, 4, 20)), (1, 2, 3), (1, 2, 3),
                                                            (1, 2, 4)):
        indices = np.setdiff1d(np.arange(n), gaps)
        counts, seen = set(), []
        for rank in range(ranks):
            total = 0
            for w in range(workers):
                units = shuffle_units(indices, block, Slot(rank, ranks, w, workers), 3, 2, pad=True)
                k = sum(len(u) for u in units)
                total += -(-k // batch)  # each worker batches its own share
                seen += np.concatenate(units).tolist() if units else []
            counts.add(total)
        assert len(counts) == 1, (n, gaps, ranks, workers, batch, counts)
        assert set(seen) == set(indices.tolist())  # padding repeats, never loses a sample
