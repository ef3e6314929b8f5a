"""The task model of `occdata.runtime.cluster.run_tasks`, and what runs around a task on a worker.

- `Task`: a small frozen, picklable record (never the data) with `units` (its share of the progress
  bar; 0: not counted) and `run(should_stop)`, which does the work and returns small metadata.
  `should_stop()` raises `Interrupted` once the run is being stopped (a no-op on a Dask worker):
  a long task calls it only where stopping is safe.
- `run_on_worker(task)`: the function a Dask worker runs. It applies `worker_setup(1)`, then returns
  the task's result, or a `TaskFailed` value for the task's own exception: Dask then never carries
  a task error, so whatever error reaches the client is the cluster's (a lost scheduler, ...).
- `run_pickled_on_worker(blob)`: the same for a task the client pickled itself (`pickle_task`): Dask
  carries one opaque bytes frame, so its scheduler neither unpickles the task nor re-pickles it, and
  no frame is made per numpy array in it.
- `worker_setup(threads)`: every thread limit in one place (numba, OpenCV, the BLAS/OpenMP
  environment) and the allocator (`occdata.runtime.allocator`), idempotent, for LocalCluster
  workers, `--scheduler` workers and in-process runs.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable
from typing import Any, NoReturn, Protocol, TypeVar

from occdata.runtime.allocator import tune_allocator

__all__ = ["ZARR_POOL_ENV", "StopCheck", "Task", "TaskFailed", "no_stop", "pickle_task", "run_on_worker",
           "run_pickled_on_worker", "worker_setup"]

R_co = TypeVar("R_co", covariant=True)
StopCheck = Callable[[], None]
_THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
_MAX_MESSAGE = 2000  # characters of a task's error message carried back
ZARR_POOL_ENV = {"ZARR_THREADING__MAX_WORKERS": "1"}  # zarr's config from the environment: one codec thread


class Task(Protocol[R_co]):
    """What `run_tasks` runs (see the module docstring)."""

    @property
    def units(self) -> int: ...

    def run(self, should_stop: StopCheck) -> R_co: ...


def no_stop() -> None:
    """The stop check of a task on a Dask worker: only the client acts on Ctrl-C / SIGTERM."""


class TaskFailed(Exception):
    """A task's own exception, raised on a worker: its type name, message and, when it pickles, the
    exception itself (re-raised in the client by `reraise`, so callers see the task's error type)."""

    def __init__(self, kind: str, message: str, error: BaseException | None = None) -> None:
        super().__init__(f"{kind}: {message}")
        self.kind, self.message, self.error = kind, message, error

    def __reduce__(self) -> tuple[Any, ...]:
        return TaskFailed, (self.kind, self.message, self.error)

    @classmethod
    def of(cls, exc: BaseException) -> TaskFailed:
        message = str(exc)[:_MAX_MESSAGE]
        try:  # carried back only when it survives the trip
            pickle.loads(pickle.dumps(exc))  # noqa: S301 - our own object, just pickled here
            error: BaseException | None = exc
        except Exception:  # noqa: BLE001 - an exception holding a lock, a file handle, ...
            error = None
        return cls(type(exc).__name__, message, error)

    def reraise(self) -> NoReturn:
        if self.error is not None:
            raise self.error
        raise self


_process_threads: int | None = None  # what `worker_setup` last applied process-wide


def worker_setup(threads: int | None) -> None:
    """Thread limits for the tasks of this process. `threads` per task (a Dask worker runs one task
    per thread, one thread per core: numba or OpenCV pools on top oversubscribed the cores and took
    3-4x the time); None: the libraries' defaults (one task at a time, in the client process).
    Idempotent and cheap: called before every task, since numba's setting is per thread."""
    global _process_threads
    import numba

    tune_allocator()  # once per process: keeps freed sample buffers instead of faulting pages back in

    # `set_num_threads` only, never the NUMBA_NUM_THREADS variable: numba re-reads it at every compile
    # and refuses a value other than its pool's size, so a later change to the environment broke
    # every compile in the process.
    n = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(n if threads is None else max(1, min(threads, n)))
    if threads is None or _process_threads == threads:  # None: the process-wide defaults are left alone
        return
    for name in _THREAD_ENV:  # BLAS / OpenMP pools started from now on (the nanny sets these at spawn)
        os.environ[name] = str(threads)
    _limit_zarr_pool(threads)
    try:
        import cv2

        cv2.setNumThreads(threads)
    except ImportError:
        pass
    _process_threads = threads


def _limit_zarr_pool(threads: int) -> None:
    """zarr's codec pool (compression runs there) to `threads`: by default it starts cores + 4
    threads in each worker, on top of the task's own, so two one-core workers ran up to 12 codec
    threads on two cores. Binds only before zarr's first read or write in this process (it makes the
    pool once); LocalCluster workers get it from their environment (`ZARR_POOL_ENV`)."""
    import zarr

    zarr.config.set({"threading.max_workers": threads})


def run_on_worker(task: Task[R_co]) -> R_co | TaskFailed:
    """Run `task` on a Dask worker: its result, or its own exception as a returned `TaskFailed`."""
    worker_setup(1)
    try:
        return task.run(no_stop)
    except Exception as exc:  # noqa: BLE001 - the task's error, told apart from the cluster's by type
        return TaskFailed.of(exc)


def pickle_task(task: Task[Any]) -> bytes:
    """`task` as one bytes object, numpy arrays in-band. A Dask task holding the task itself costs the
    client's event loop ~35 ms a task at a build's 32 samples (~150 arrays): the scheduler unpickles
    it, pickles it again for the worker, and sends and meters one frame per array."""
    return pickle.dumps(task, protocol=pickle.HIGHEST_PROTOCOL)


def run_pickled_on_worker(blob: bytes) -> Any:
    """`run_on_worker` on a task from `pickle_task` (made by this program's own client, never read
    from user data)."""
    return run_on_worker(pickle.loads(blob))  # noqa: S301 - our own client's task, see above
