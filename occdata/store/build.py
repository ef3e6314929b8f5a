"""`occdata build`: a nuScenes-format tree (+ Occ3D labels) -> one chunked zarr store.

The work runs as tasks on Dask (`occdata.runtime.cluster`): one block of `--block-samples` samples per task,
aligned to the store's chunks and shards, each task writing its own chunks (`occdata.store.blocks`):
many writers, every byte written once, in any order. Before any task runs, this process plans where
each block's ragged payload goes from the inputs alone (`occdata.store.plan`); only errors and sizes
travel back, and this process owns the metadata. A sample is complete only once its state flag says
so; `--resume` converts the blocks not done and gives a store identical to an uninterrupted build, for
any number of workers. The parts: `config` (options), `inputs` (what is read), `identity` (what a
resume must match), `create` (the store's layout), `plan` (the client side of a run).
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from occdata.errors import OccDataError
from occdata.nuscenes.rig import NUSCENES_RIG, Rig
from occdata.runtime.cluster import LazyTasks, cluster_client, run_tasks
from occdata.runtime.lock import Fence, LeaseLostError, StoreLock, store_lock
from occdata.runtime.storage import is_remote
from occdata.store.blocks import BlockSummary, ConvertJob, sample_checksums
from occdata.store.config import ROOT_GTS, BuildConfig, GtsDefault, LabelsSource
from occdata.store.create import STAGING_SUFFIX, consolidate, grow_flat, open_or_create, resume_state, store_exists
from occdata.store.identity import identity_diff
from occdata.store.inputs import BuildInputs, check_sweep_files, find_label_files, read_inputs
from occdata.store.layout import REGIONS, STATE_DONE, STATE_ERROR, STATE_PENDING
from occdata.store.pack import write_pack
from occdata.store.plan import (
    Coordinator,
    Span,
    block_spans,
    blocks_todo,
    payload_bounds,
    plan_regions,
    relocate,
    reset_blocks,
)
from occdata.store.reader import store_location

__all__ = ["ROOT_GTS", "STAGING_SUFFIX", "BuildConfig", "BuildReport", "GtsDefault", "LabelsSource", "build_store",
           "check_sweep_files", "consolidate", "find_label_files", "identity_diff",
           "sample_checksums"]


@dataclass(frozen=True)
class BuildReport:
    store: Path
    n_samples: int
    n_done: int
    n_errors: int
    n_labelled: int
    processed_now: int
    warnings: tuple[str, ...] = ()  # from reading the tables (identical duplicates, nbr_samples)
    flow: bool = False  # the labels were OpenOcc v2 files: the store has labels/flow
    rig: Rig = NUSCENES_RIG  # the cameras and LiDARs stored; `rig.left_out` names the sensors that were not


def build_store(config: BuildConfig, client: Any = None) -> BuildReport:
    """Build (or resume) a store. Raises `OccDataError` on bad inputs or, with on_error=fail, at the
    first bad sample, after committing every sample before it; `occdata.runtime.cluster.Interrupted`
    on Ctrl-C/SIGTERM. `client`: a `distributed.Client` to use (default: one for `config.cluster`,
    closed at the end)."""
    inputs = read_inputs(config)  # before anything is written
    with store_lock(config.out, "build") as lock:
        try:
            with contextlib.nullcontext(client) if client is not None else cluster_client(config.cluster) as run_on:
                return _build_locked(config, run_on, inputs, lock)
        except OSError as exc:  # a full disk, a read-only folder: committed samples are kept
            where = f" ({exc.filename})" if exc.filename else ""
            raise OccDataError(
                f"cannot write the store {config.out}: {exc.strerror or exc}{where}. Everything committed so far "
                "is kept; fix the cause and rerun with --resume"
            ) from None


def _build_locked(config: BuildConfig, client: Any, inputs: BuildInputs, lock: StoreLock) -> BuildReport:
    """The build under the store's lock; `lock.check()` raises once the lock is lost (an S3 lease that
    lapsed): polled while tasks run and before the final commit. Tasks carry `lock.fence`; a run that
    stops early revokes it and waits for its tasks (`run_tasks`) before writing any metadata."""
    resumed = store_exists(store_location(config.out))
    spans = block_spans(len(inputs.ds.samples), config.block_samples)

    def plan() -> np.ndarray:  # a new store's regions, from the tables and the files' sizes
        return plan_regions(payload_bounds(inputs.ds.samples, inputs.histories, config.options), spans)

    root, out = open_or_create(config, inputs.ds, list(inputs.split_names), inputs.gts, plan, inputs.label_format)
    state = resume_state(root)
    todo = blocks_todo(state, spans)
    if todo and root.attrs.get("complete"):
        root.attrs["complete"] = False  # until this run has committed them again
    reset_blocks(root, state, spans, todo, every=resumed)
    regions = root[REGIONS][:]
    grow_flat(root, regions)  # a run killed between a relocation and the grow
    consolidate(out)  # what every task reads first: current before any task runs
    coord = Coordinator(config.on_error)
    try:
        converted = _run_waves(config, client, inputs, root, out, state, todo, regions, coord, lock)
        lock.check()
    except LeaseLostError:
        raise  # another writer may hold the store now: nothing more is written
    except BaseException:  # Ctrl-C, a lost scheduler, --on-error fail, a bug: keep the reasons found so far
        lock.revoke()  # run_tasks did so before its wait; here also for a stop between waves or in-process
        if coord.errors:
            with contextlib.suppress(Exception):  # e.g. the disk that just filled up: the first error counts
                root.attrs["errors"] = coord.recorded()
                consolidate(out)
        raise
    return _finish(config, root, out, inputs, coord, converted)


def _run_waves(config: BuildConfig, client: Any, inputs: BuildInputs, root: zarr.Group, out: str,
               state: np.ndarray, todo: set[int], regions: np.ndarray, coord: Coordinator,
               lock: StoreLock) -> int:
    """The tasks, in at most two waves (the second: blocks that outgrew their region); returns the
    samples converted. No metadata is written while tasks run (see `Coordinator`)."""
    spans = block_spans(len(inputs.ds.samples), config.block_samples)
    converted = [0]

    def on_result(job: ConvertJob, result: BlockSummary) -> list[ConvertJob]:
        if result.placed:  # samples that needed work (a block's done ones are redone with it)
            converted[0] += int((state[job.i0 : job.i1] != STATE_DONE).sum())
        return coord.add(result)

    tok_width = int(root["sample/token"].shape[-1])
    wave = sorted(todo)
    for attempt in range(2):  # the second wave: blocks that outgrew their region, in their new one
        # Each task made when it is sent: all of them made up front held ~5 KB per sample (static arrays).
        jobs = LazyTasks([spans[b] for b in wave],
                         functools.partial(_convert_job, config, inputs, out, regions=regions, tok_width=tok_width,
                                           fence=lock.fence))
        run_tasks(client, jobs, desc="build", unit="sample", progress=config.progress, on_result=on_result,
                  keep=coord.keep, check=lock.check, revoke=lock.revoke,
                  total=sum(i1 - i0 for _, i0, i1 in jobs.items))
        if not coord.outgrown:
            break
        if attempt:
            raise OccDataError(f"blocks {sorted(coord.outgrown)} changed size while this build ran (their input "
                               "files were rewritten); rerun with --resume once the input is still")
        wave, regions = sorted(coord.outgrown), relocate(regions, coord.outgrown)
        coord.outgrown = {}
        root[REGIONS][...] = regions  # the new regions first: a resume finds them there
        grow_flat(root, regions)
        consolidate(out)
    if coord.failure is not None:
        i, token, reason = coord.failure
        raise OccDataError(
            f"sample {i} ({token}) failed: {reason}. Everything before it is committed; fix the input and rerun "
            "with --resume (or use --on-error skip)."
        )
    return converted[0]


def _convert_job(config: BuildConfig, inputs: BuildInputs, out: str, span: Span, regions: np.ndarray,
                 tok_width: int, fence: Fence) -> ConvertJob:
    b, i0, i1 = span
    return ConvertJob(out, b, i0, i1, tuple(inputs.sample_input(i, config, tok_width) for i in range(i0, i1)),
                      tuple((int(a), int(e)) for a, e in regions[b]), config.on_error, fence)


def _finish(config: BuildConfig, root: zarr.Group, out: str, inputs: BuildInputs, coord: Coordinator,
            processed: int) -> BuildReport:
    """The final commit (idempotent, in no block order): completeness, the run's options and errors,
    metadata."""
    final_state = root["status/state"][:]
    complete = bool((final_state != STATE_PENDING).all())
    write_pack(root)  # the small arrays in one chunk each, for readers (occdata.store.pack)
    root.attrs.update({"complete": complete, "errors": coord.recorded(),
                       "build_config": {"workers": config.cluster.workers, "on_error": config.on_error}})
    consolidate(out)
    return BuildReport(
        store=Path(out) if not is_remote(out) else out,  # type: ignore[arg-type]
        n_samples=len(inputs.ds.samples),
        n_done=int((final_state == STATE_DONE).sum()),
        n_errors=int((final_state == STATE_ERROR).sum()),
        n_labelled=int(root["labels/present"][:].sum()),
        processed_now=processed,
        warnings=inputs.ds.warnings,
        flow=inputs.flow,
        rig=inputs.ds.rig,
    )
