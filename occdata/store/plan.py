"""The client side of a build run: which blocks to (re)build, and the `Coordinator` that places
converted blocks in the flat arrays in block order and hands back their commit jobs."""

from __future__ import annotations

from typing import Any

import numpy as np
import zarr
from zarr.core.sync import sync

from occdata.store.blocks import BlockSummary, CommitJob, ConvertJob, Placer, flat_footprint, open_flat
from occdata.store.create import consolidate
from occdata.store.layout import FLAT_ARRAYS, FLAT_OF_OFFSETS, STATE_DONE, STATE_PENDING

__all__ = ["Coordinator", "Span", "align", "block_spans", "blocks_todo", "committed_end", "reset_blocks",
           "set_flat_length"]

Span = tuple[int, int, int]  # (block, first sample, end sample)


def align(n: int, chunk: int) -> int:
    return -(-n // chunk) * chunk


def block_spans(n: int, block_samples: int) -> list[Span]:
    return [(b, i0, min(i0 + block_samples, n)) for b, i0 in enumerate(range(0, n, block_samples))]


def blocks_todo(state: np.ndarray, spans: list[Span]) -> set[int]:
    """Blocks with a sample not done (`state`: `(n,) uint8` commit flags): rebuilt whole."""
    return {b for b, i0, i1 in spans if (state[i0:i1] != STATE_DONE).any()}


class Coordinator:
    """Places converted blocks in block order and hands back their commit jobs; records errors
    (skip) or stops at the first failed sample (fail)."""

    def __init__(self, root: zarr.Group, out: str, staging: str, spans: list[Span], todo: set[int],
                 on_error: str) -> None:
        self.root, self.out, self.staging, self.spans, self.todo = root, out, staging, spans, todo
        self.on_error = on_error
        self.summaries: dict[int, BlockSummary] = {}
        self.next = 0  # position in spans of the next block to place
        self.failure: tuple[int, str, str] | None = None
        self.errors: list[dict[str, Any]] = []
        self.footprints: dict[str, dict[int, tuple[int, int] | None]] = {}
        self.placers: dict[str, Placer] = {}
        for off_name, flat_name in FLAT_OF_OFFSETS.items():
            chunk = FLAT_ARRAYS[flat_name][2]
            offsets = root[off_name][:] if len(todo) < len(spans) else None
            fp = {b: flat_footprint(offsets[i0:i1], chunk) for b, i0, i1 in spans if b not in todo} if (
                offsets is not None) else {}
            self.footprints[flat_name] = fp
            self.placers[flat_name] = Placer(chunk, [f for f in fp.values() if f is not None])

    def keep(self, job: ConvertJob | CommitJob) -> bool:
        """After a failure under --on-error fail, blocks after the failed one are not converted. (A
        commit job exists only for a block placed before any later failure: always kept.)"""
        return self.failure is None or job.i0 <= self.failure[0]

    def add(self, summary: BlockSummary) -> list[CommitJob]:
        """A converted block: the commit jobs of every block that can now be placed, in block order."""
        self.summaries[summary.block] = summary
        if self.on_error == "fail" and summary.errors:
            first = min(summary.errors)
            if self.failure is None or first[0] < self.failure[0]:
                self.failure = first
        jobs: list[CommitJob] = []
        while self.next < len(self.spans):
            b, i0, i1 = self.spans[self.next]
            if b not in self.todo:
                for name, placer in self.placers.items():
                    placer.skip(self.footprints[name].get(b))
                self.next += 1
                continue
            s = self.summaries.get(b)
            if s is None or (self.failure is not None and i0 > self.failure[0]):
                break
            jobs.append(self._place(s, i0, i1))
            self.next += 1
        return jobs

    def _place(self, s: BlockSummary, i0: int, i1: int) -> CommitJob:
        starts = {name: placer.place(s.rows[name]) for name, placer in self.placers.items()}
        grown = False
        for name, placer in self.placers.items():  # the client alone writes metadata
            arr = open_flat(self.out, name)
            if arr.shape[0] < placer.high:  # grow by doubling: few metadata rewrites (trimmed at the end)
                step = max(placer.high, 2 * arr.shape[0], 16 * arr.chunks[0])
                arr.resize((align(step, arr.chunks[0]), *arr.shape[1:]))
                grown = True
        if grown:
            consolidate(self.out)
        until = i1
        if self.failure is not None and i0 <= self.failure[0] < i1:
            until = self.failure[0]
        elif s.errors:  # skip: the errors are recorded before the block's state says "error"
            self.errors += [{"index": int(i), "token": t, "reason": r} for i, t, r in s.errors]
            self.root.attrs["errors"] = sorted(self.errors, key=lambda e: e["index"])
        return CommitJob(self.out, self.staging, s.block, i0, i1, starts, until)


def set_flat_length(out: str, name: str, rows: int) -> None:
    """The final length of a flat array (grown by steps during the build); a shrink deletes nothing
    (no chunk lies beyond the placed blocks), so it costs one metadata write, not a listing."""
    arr = open_flat(out, name)
    if arr.shape[0] == rows:
        return
    try:
        sync(arr._async_array.resize((rows, *arr.shape[1:]), delete_outside_chunks=False))
    except TypeError:  # a zarr without that option
        arr.resize((rows, *arr.shape[1:]))


def reset_blocks(root: zarr.Group, state: np.ndarray, spans: list[Span], todo: set[int], every: bool) -> None:
    """Blocks to (re)build are pending again before any of their data moves; their old errors go.
    `every` (a resumed store): also write the flags that are pending already, so that a store from
    before issue 24 (no state chunk for its pending tail) has every state chunk from now on."""
    arr = root["status/state"].with_config({"write_empty_chunks": True})
    for b, i0, i1 in spans:
        if b in todo and (every or (state[i0:i1] != STATE_PENDING).any()):
            arr[i0:i1] = np.zeros(i1 - i0, dtype=np.uint8)
    if root.attrs.get("errors"):
        root.attrs["errors"] = []


def committed_end(root: zarr.Group, flat_name: str) -> int:
    """The end of the last range that a committed sample uses in a flat array (chunk-aligned)."""
    off_name = next(o for o, f in FLAT_OF_OFFSETS.items() if f == flat_name)
    off = root[off_name][:]
    used = off[..., 1] > 0
    end = int((off[..., 0] + off[..., 1])[used].max()) if used.any() else 0
    return align(end, FLAT_ARRAYS[flat_name][2])
