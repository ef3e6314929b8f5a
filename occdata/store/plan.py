"""The client side of a build run: which blocks to (re)build, where each block's ragged payload goes
(planned from the inputs before any task runs), and the `Coordinator` that takes the tasks' summaries
in any order.

The plan: every sample gets an upper bound on its rows in each flat array, from the tables and the
files' sizes only (`payload_bounds`); block b's region is the sum of its samples' bounds, rounded up
to whole chunks, and the regions follow each other in block order (`plan_regions`). A task writes its
payload at the start of its region; the chunks its payload does not reach are never written, so a
generous bound costs address space, not bytes. The plan is stored (`plan/regions`) when the store is
created, so a resume uses the same one whatever happened to the files since."""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from occdata.errors import OccDataError
from occdata.nuscenes import LidarRecord, SampleRecord
from occdata.nuscenes.pointfiles import is_pcd, pcd_point_count
from occdata.store.blocks import BlockSummary, ConvertJob
from occdata.store.layout import FLAT_ARRAYS, STATE_DONE, STATE_PENDING
from occdata.store.sample import SampleOptions

__all__ = ["LIDAR_POINT_BYTES", "Coordinator", "Span", "align", "block_spans", "blocks_todo", "jpeg_bound",
           "payload_bounds", "plan_regions", "relocate", "reset_blocks"]

Span = tuple[int, int, int]  # (block, first sample, end sample)
LIDAR_POINT_BYTES = 20  # a .pcd.bin point: x, y, z, intensity, ring as float32
JPEG_HEADER_BYTES = 1 << 16  # markers, tables and a few APP segments on top of the pixel bound


def align(n: int, chunk: int) -> int:
    return -(-n // chunk) * chunk


def block_spans(n: int, block_samples: int) -> list[Span]:
    return [(b, i0, min(i0 + block_samples, n)) for b, i0 in enumerate(range(0, n, block_samples))]


def blocks_todo(state: np.ndarray, spans: list[Span]) -> set[int]:
    """Blocks with a sample not done (`state`: `(n,) uint8` commit flags): rebuilt whole."""
    return {b for b, i0, i1 in spans if (state[i0:i1] != STATE_DONE).any()}


def jpeg_bound(width: int, height: int, scale: float = 1.0) -> int:
    """Bytes planned for one stored JPEG of a `width` x `height` image (`scale`: --image-scale): the
    raw RGB size of the stored image plus headers. From the tables alone, so a file fixed between
    runs (a truncated JPEG replaced) keeps its block's region; a stream larger than that (noise at
    quality 100) is legal and moves its block to the end of the array (`relocate`)."""
    if scale != 1.0:
        width, height = round(width * scale), round(height * scale)
    return 3 * int(width) * int(height) + JPEG_HEADER_BYTES


def _points(path: Path) -> int:
    """LiDAR points in a file: a `.pcd.bin` / `.bin` by its size, a `.pcd` by its header's POINTS; 0 if
    it cannot be read now (such a sample fails; if it is fixed later and succeeds, its block moves to
    the end: `relocate`)."""
    try:
        if is_pcd(path):
            return pcd_point_count(path)
        return os.stat(path).st_size // LIDAR_POINT_BYTES
    except (OSError, OccDataError):
        return 0


def payload_bounds(samples: Sequence[SampleRecord], histories: Sequence[tuple[LidarRecord, ...]],
                   options: SampleOptions, threads: int = 16, window: int = 1024) -> np.ndarray:
    """`(n, len(FLAT_ARRAYS)) int64` rows planned per sample in each flat array: JPEG bytes from the
    image sizes in the tables (`jpeg_bound`); depth rows = cameras x the points of every LiDAR's
    keyframe sweep and of each history sweep (a point can land in several cameras), from the files'
    sizes (one stat per distinct file of a `window` of samples, in `threads` threads: a network file
    system answers slowly; windows keep the memory independent of the sample count)."""
    out = np.zeros((len(samples), len(FLAT_ARRAYS)), dtype=np.int64)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for w0 in range(0, len(samples), window):
            w1 = min(w0 + window, len(samples))
            part = [(samples[i], histories[i]) for i in range(w0, w1)]
            files = list(dict.fromkeys(p for s, h in part for p in (*(r.path for r in s.lidars), *(r.path for r in h))))
            points = dict(zip(files, pool.map(_points, files), strict=True))
            for i, (s, h) in enumerate(part, start=w0):
                for f, name in enumerate(FLAT_ARRAYS):
                    if name == "images/jpeg":
                        out[i, f] = sum(jpeg_bound(c.width, c.height, options.image_scale) for c in s.cameras)
                    else:
                        out[i, f] = len(s.cameras) * sum(points[r.path] for r in (*s.lidars, *h))
    return out


def plan_regions(bounds: np.ndarray, spans: list[Span]) -> np.ndarray:
    """`(n_blocks, len(FLAT_ARRAYS), 2) int64` [start, end) rows of each block's region: its samples'
    `bounds` `(n, F)` summed, rounded up to whole chunks, blocks one after the other."""
    out = np.zeros((len(spans), len(FLAT_ARRAYS), 2), dtype=np.int64)
    for f, (_, _, chunk) in enumerate(FLAT_ARRAYS.values()):
        sizes = np.array([align(int(bounds[i0:i1, f].sum()), chunk) for _, i0, i1 in spans], dtype=np.int64)
        ends = np.cumsum(sizes)
        out[:, f, 0], out[:, f, 1] = ends - sizes, ends
    return out


def relocate(regions: np.ndarray, needs: dict[int, tuple[int, ...]]) -> np.ndarray:
    """`regions` with new ones, after the current end of each flat array and in block order, for the
    blocks whose payload (`needs`: rows per flat array) outgrew their region (an input file that grew
    since the plan was made). The old region stays reserved: nothing else is ever put there."""
    out = regions.copy()
    for f, (_, _, chunk) in enumerate(FLAT_ARRAYS.values()):
        end = int(out[:, f, 1].max()) if len(out) else 0
        for b in sorted(needs):
            if needs[b][f] > out[b, f, 1] - out[b, f, 0]:
                out[b, f] = (end, end + align(needs[b][f], chunk))
                end = int(out[b, f, 1])
    return out


class Coordinator:
    """Takes the block summaries in any order: under --on-error skip it keeps the errors here, in the
    client, for the one write of `attrs["errors"]` after the tasks (`recorded`): a root-attributes
    write while tasks run drops the consolidated metadata that every task opens, and a task reading
    `zarr.json` while it is rewritten can see half of it. Under fail it keeps the first failed
    sample, and blocks after it are no longer started. Blocks that outgrew their region are kept for
    `relocate`."""

    def __init__(self, on_error: str) -> None:
        self.on_error = on_error
        self.failure: tuple[int, str, str] | None = None
        self.errors: list[dict[str, Any]] = []
        self.outgrown: dict[int, tuple[int, ...]] = {}

    def keep(self, job: ConvertJob) -> bool:
        """After a failure under --on-error fail, blocks after the failed sample are not started."""
        return self.failure is None or job.i0 <= self.failure[0]

    def add(self, summary: BlockSummary) -> list[ConvertJob]:
        """One finished task; never any follow-up job (relocated blocks run after this wave)."""
        if not summary.placed:
            self.outgrown[summary.block] = summary.needs
            return []
        if self.on_error == "fail" and summary.errors:
            first = min(summary.errors)
            if self.failure is None or first[0] < self.failure[0]:
                self.failure = first
        elif summary.errors:
            self.errors += [{"index": int(i), "token": t, "reason": r} for i, t, r in summary.errors]
        return []

    def recorded(self) -> list[dict[str, Any]]:
        """The errors of this run in sample order, as `attrs["errors"]` holds them."""
        return sorted(self.errors, key=lambda e: e["index"])


def reset_blocks(root: zarr.Group, state: np.ndarray, spans: list[Span], todo: set[int], every: bool) -> None:
    """Blocks to (re)build are pending again before any of their data moves; their old errors go.
    `every` (a resumed store): also write the flags that are pending already, so that every state
    chunk exists from now on."""
    arr = root["status/state"].with_config({"write_empty_chunks": True})
    for b, i0, i1 in spans:
        if b in todo and (every or (state[i0:i1] != STATE_PENDING).any()):
            arr[i0:i1] = np.zeros(i1 - i0, dtype=np.uint8)
    if root.attrs.get("errors"):
        root.attrs["errors"] = []
