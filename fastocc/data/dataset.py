"""`StoreDataset`: a torch IterableDataset streaming Batches from an occdata store.

Use with `DataLoader(ds, batch_size=None, num_workers=W, pin_memory=...)`: the dataset batches
itself (inside the workers), so that scene-sequential order can lay samples out in batch slots.
Call `ds.set_epoch(e)` before each epoch (with persistent_workers=False, so workers see it).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from fastocc._worker_signals import ignore_stop_signals
from fastocc.data.batch import Batch, collate
from fastocc.data.order import Slot, sequential_batches, shuffle_units
from fastocc.data.sample import RawSample, SampleConfig, SampleMaker, StoreSamples
from fastocc.data.workers import check_main_guard, default_worker_context
from occdata.errors import OccDataError
from occdata.store.reader import open_store

__all__ = ["LoaderConfig", "StoreDataset", "load_batch", "loader_batches", "make_loader"]


@dataclass(frozen=True)
class LoaderConfig:
    """What to stream and how.

    store: local path or fsspec URL. sequential: scene-sequential order (temporal training) instead of
    shuffled. splits: split names to keep (empty = all). rank/world_size: None = from
    torch.distributed when initialised, else 0/1. pad: top up shuffled slots to equal counts
    (order.py). equal_lanes: scene-sequential lanes cut to one common length, so every rank yields the
    same number of full batches (training; drops < ranks x batch_size samples per epoch, order.py);
    False = every sample exactly once (evaluation). sample: image/BEV augmentation (train flags there)
    and depth-target settings.
    skip_batches: the first k batches of the epoch (as this rank would yield them) are planned but not
    decoded; worker roles rotate by k so that a DataLoader's round robin continues the original order.
    limit_samples: keep only the first N selected samples (store order); 0 = all.
    """

    store: str | Path
    batch_size: int = 1
    sequential: bool = False
    sample: SampleConfig = field(default_factory=SampleConfig)
    splits: tuple[str, ...] = ()
    seed: int = 0
    shuffle_buffer: int = 64
    segment_len: int | None = None
    rank: int | None = None
    world_size: int | None = None
    pad: bool = False
    equal_lanes: bool = False
    drop_last: bool = False
    skip_batches: int = 0  # start the epoch at this rank's batch k (exact resume); skipped ones are not decoded
    limit_samples: int = 0  # > 0: only the first N samples of the selection (smoke runs, tests)

    def __post_init__(self) -> None:
        if isinstance(self.batch_size, bool) or not isinstance(self.batch_size, int) or self.batch_size < 1:
            raise OccDataError(f"batch_size must be an integer >= 1, got {self.batch_size!r}")


class StoreDataset(IterableDataset):
    def __init__(self, config: LoaderConfig) -> None:
        super().__init__()
        self.config = config
        self.epoch = 0
        # Opened and read here, once: workers get the small arrays in shared memory (StoreSamples).
        self._samples: StoreSamples = StoreSamples(open_store(config.store, packed=True))
        self.indices = self._select(self._samples.reader)
        if config.drop_last and 0 < len(self.indices) < config.batch_size:
            # An epoch of zero batches is never what was meant: refuse rather than train on nothing.
            raise OccDataError(f"drop_last with {len(self.indices)} samples and batch_size {config.batch_size} "
                               "would yield no batch; lower batch_size or turn drop_last off")

    def _select(self, reader) -> np.ndarray:
        # Built samples only (pending / failed ones are never yielded), the first `limit_samples` if set.
        indices = reader.split_indices(self.config.splits or None)
        return indices[: self.config.limit_samples] if self.config.limit_samples else indices

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _slot(self) -> Slot:
        c = self.config
        rank, world = c.rank, c.world_size
        if rank is None or world is None:
            dist = torch.distributed
            if dist.is_available() and dist.is_initialized():
                rank, world = dist.get_rank(), dist.get_world_size()
            else:
                rank, world = 0, 1
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info is not None else (0, 1)
        # The DataLoader asks worker 0 first; after k batches the original order continues with role k % W.
        return Slot(rank, world, (worker + c.skip_batches) % n_workers, n_workers)

    def _skip(self, slot: Slot) -> int:
        """How many of this slot's batches fall among the rank's first `skip_batches` (t = worker + j W)."""
        return max(0, -(-(self.config.skip_batches - slot.worker) // slot.num_workers))

    def samples(self) -> StoreSamples:
        self._samples = self._samples.for_this_process()  # a forked worker: its own store handle
        return self._samples

    def __len__(self) -> int:
        """Samples per epoch over all ranks (exactly-once; padding excluded)."""
        return len(self.indices)

    def num_batches(self, num_workers: int) -> int:
        """Batches this rank yields in the current epoch (`set_epoch`) with `num_workers` loader workers,
        from the same plan functions the workers use (order.py); `skip_batches` not subtracted."""
        c, s = self.config, self.samples()
        rank, world = self._slot().rank, self._slot().world_size
        total = 0
        for w in range(max(1, num_workers)):
            slot = Slot(rank, world, w, max(1, num_workers))
            if c.sequential:
                plan = sequential_batches(self.indices, s.scene_index, slot, c.batch_size, c.seed, self.epoch,
                                          c.segment_len, equal_lanes=c.equal_lanes)
                total += sum(1 for e in plan if not (c.drop_last and len(e) < c.batch_size))
            else:
                n = sum(len(u) for u in shuffle_units(self.indices, s.block, slot, c.seed, self.epoch, pad=c.pad))
                total += n // c.batch_size if c.drop_last else -(-n // c.batch_size)
        return total

    def __iter__(self) -> Iterator[Batch]:
        if get_worker_info() is not None:
            cv2.setNumThreads(1)  # one core per worker; OpenCV's own pool would oversubscribe
            ignore_stop_signals()  # the trainer stops us; torch's own SIGTERM handler would kill us first
        slot = self._slot()
        if self.config.sequential:
            yield from self._iter_sequential(slot)
        else:
            yield from self._iter_shuffled(slot)

    def _rng(self, index: int) -> np.random.Generator | None:
        # Keyed by the sample, not the worker: augmentation is the same whatever the sharding.
        return np.random.default_rng([self.config.seed, self.epoch, index])

    def _iter_shuffled(self, slot: Slot) -> Iterator[Batch]:
        c, s = self.config, self.samples()
        make = SampleMaker(s, c.sample)
        units = _LazyUnits(s, shuffle_units(self.indices, s.block, slot, c.seed, self.epoch, pad=c.pad))
        rng = np.random.default_rng([c.seed, self.epoch, slot.rank, slot.worker, 2])
        buffer: list[tuple[int, int]] = []  # (unit, store index): the payload is read when taken
        batch: list[tuple[int, int]] = []
        skip = [self._skip(slot)]

        def full() -> Iterator[Batch]:
            if skip[0] > 0:  # planned, never read nor decoded
                skip[0] -= 1
                for u, _ in batch:
                    units.release(u)
            else:
                raws = [units.take(u, i) for u, i in batch]
                yield collate([make(r, self._rng(r.index)) for r in raws])
            batch.clear()

        emitted = [0]

        def emit(entry: tuple[int, int]) -> Iterator[Batch]:
            batch.append(entry)
            if len(batch) == c.batch_size:
                emitted[0] += 1
                yield from full()

        for u, unit in enumerate(units.units):
            buffer.extend((u, int(i)) for i in unit)
            while len(buffer) > c.shuffle_buffer:
                k = int(rng.integers(len(buffer)))
                buffer[k], buffer[-1] = buffer[-1], buffer[k]
                yield from emit(buffer.pop())
        order = rng.permutation(len(buffer))
        for k in order:
            yield from emit(buffer[k])
        if batch and not c.drop_last:
            yield from full()
        elif batch and not emitted[0]:
            _warn_all_dropped(len(batch), c.batch_size, slot)

    def _iter_sequential(self, slot: Slot) -> Iterator[Batch]:
        c, s = self.config, self.samples()
        make = SampleMaker(s, c.sample)
        plan = sequential_batches(self.indices, s.scene_index, slot, c.batch_size, c.seed, self.epoch,
                                  c.segment_len, equal_lanes=c.equal_lanes)
        dropped = sum(len(e) for e in plan if c.drop_last and len(e) < c.batch_size)
        if dropped and dropped == sum(len(e) for e in plan):
            _warn_all_dropped(dropped, c.batch_size, slot)
        for entries in plan[self._skip(slot):]:
            if c.drop_last and len(entries) < c.batch_size:
                continue
            out = []
            for idx, start in entries:
                (raw,) = s.read_run(idx, idx + 1)
                out.append(make(raw, self._rng(idx), seq_start=start))
            yield collate(out)


class _LazyUnits:
    """The shuffled order's units (blocks), each read whole (one read per array) when the first of its
    samples is taken, and dropped once every entry of it is taken or released. The order is planned on
    indices alone, so the first batch waits for one block, not for the shuffle buffer's fill of blocks,
    and skipped batches (`skip_batches`) are never read."""

    def __init__(self, samples: StoreSamples, units: list[np.ndarray]) -> None:
        self.samples, self.units = samples, units
        self.left = [len(u) for u in units]  # entries not yet taken or released (padding may repeat one)
        self.loaded: dict[int, dict[int, RawSample]] = {}

    def take(self, u: int, index: int) -> RawSample:
        if u not in self.loaded:
            uniq = np.unique(self.units[u])
            runs = self.samples.read_run(int(uniq[0]), int(uniq[-1]) + 1, set(uniq.tolist()))
            self.loaded[u] = {r.index: r for r in runs}
        raw = self.loaded[u][index]
        self.release(u)
        return raw

    def release(self, u: int) -> None:
        self.left[u] -= 1
        if not self.left[u]:
            self.loaded.pop(u, None)


def _warn_all_dropped(n: int, batch_size: int, slot: Slot) -> None:
    warnings.warn(f"drop_last: rank {slot.rank} worker {slot.worker} got {n} samples, fewer than batch_size "
                  f"{batch_size}, and yields no batch this epoch; use fewer workers or a smaller batch_size",
                  RuntimeWarning, stacklevel=3)


def make_loader(config: LoaderConfig, num_workers: int = 0, pin_memory: bool = False,
                **kwargs) -> torch.utils.data.DataLoader:
    """A DataLoader over `StoreDataset(config)` (batching happens in the dataset).

    Workers start from a forkserver unless `multiprocessing_context` is given (see workers.py for
    why, and for the one-line error a script without `if __name__ == "__main__":` gets).
    """
    if num_workers > 0:
        if "multiprocessing_context" not in kwargs:
            kwargs["multiprocessing_context"] = default_worker_context()
        check_main_guard(kwargs["multiprocessing_context"])  # one clear line, not a dead worker
    ds = StoreDataset(config)
    return torch.utils.data.DataLoader(ds, batch_size=None, num_workers=num_workers, pin_memory=pin_memory,
                                       **kwargs)


def loader_batches(loader: torch.utils.data.DataLoader) -> int:
    """Batches a loader made by `make_loader` yields this epoch on this rank (`StoreDataset.num_batches`)."""
    return loader.dataset.num_batches(loader.num_workers)


def load_batch(store: str | Path, indices: list[int], sample: SampleConfig, seed: int = 0, epoch: int = 0) -> Batch:
    """A Batch of the given store indices (random access; the same augmentation as the loader draws)."""
    samples = StoreSamples(open_store(store))  # a tool (show-batch): the block chunks, where damage shows
    make = SampleMaker(samples, sample)
    out = []
    for i in indices:
        samples.reader.require_done(i)  # out of range, failed (with its reason) or pending: one line
        (raw,) = samples.read_run(i, i + 1)
        out.append(make(raw, np.random.default_rng([seed, epoch, i])))
    return collate(out)
