"""Run independent, idempotent tasks on Dask distributed (the execution path of `build`, `labels`).

- `ClusterConfig`: `workers` processes of an embedded `LocalCluster` (the default, nothing to start),
  or an existing scheduler (`scheduler="tcp://host:8786"` or `$DASK_SCHEDULER_ADDRESS`). One worker
  without a scheduler runs the tasks in this process (same task functions, no cluster start-up).
- `cluster_client(config)`: a context manager that yields a `distributed.Client` (or None for the
  in-process case) and closes everything it started, also on Ctrl-C or an error.
- `run_tasks(client, tasks, ...)`: runs each task (`occdata.runtime.tasks.Task`: its own `run` and
  progress `units`; at most a window in flight), shows a tqdm bar, hands each task's small result to
  `on_result` in this process. Ctrl-C or SIGTERM cancels what is queued and raises `Interrupted`
  within seconds. A task's own exception is re-raised here. A transport or scheduler failure (a
  closed connection, a timeout, futures cancelled by a lost scheduler: `_is_infrastructure`) is the
  one line "lost the Dask scheduler ... rerun with --resume"; any other error on the way (a task
  that does not pickle, a result that does not, a bug in a call) is one `OccDataError` line naming
  its type, message and the frame that raised it, never advice to resume.

A task must be idempotent: Dask reruns it when its worker dies (`distributed.scheduler.allowed-
failures`, default 3), so it writes only what it alone owns (whole chunks, or files it publishes by
rename) and returns only small metadata, never the data. Worker processes of a `LocalCluster` exit
when this process dies (a pipe from the parent, `distributed.process`), and ignore SIGINT (the
terminal's Ctrl-C reaches the whole process group; only the client acts on it).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar, overload

from tqdm import tqdm

from occdata.errors import OccDataError
from occdata.runtime.allocator import ALLOCATOR_ENV
from occdata.runtime.tasks import ZARR_POOL_ENV, Task, TaskFailed, pickle_task, run_pickled_on_worker, worker_setup

if TYPE_CHECKING:  # distributed is imported lazily: `occdata` commands that do not run tasks stay light
    from distributed import Client, Future

__all__ = ["SCHEDULER_ENV", "WORKER_CONFIG", "ClusterConfig", "Interrupted", "LazyTasks", "cluster_client",
           "dask_setup", "run_tasks"]

SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"
DRAIN_S = 60.0  # how long a stopped run waits for the tasks its workers still run (fenced: they stop at a write)
# LocalCluster workers (the nanny hands this process's Dask config to them): no statistical profiler.
# It samples every thread's stack each 10 ms for a dashboard that no one sees here, in the worker's
# event-loop thread, next to the task (docs/scale.md, "Two workers": where the extra CPU went).
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
T = TypeVar("T", bound=Task[Any])


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) or SIGTERM stopped `run_tasks`; `signum` says which (exit status 128 + signum)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"stopped by signal {signum}")
        self.signum = signum


@dataclass(frozen=True)
class ClusterConfig:
    """Where tasks run. `scheduler` None: `$DASK_SCHEDULER_ADDRESS` if set, else a LocalCluster of
    `workers` single-threaded processes (`workers` 1: in this process)."""

    workers: int = 1
    scheduler: str | None = None
    connect_timeout_s: float | None = None  # None: Dask's distributed.comm.timeouts.connect (30 s)
    memory_limit: str = "auto"  # per LocalCluster worker

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise OccDataError(f"--workers must be >= 1, got {self.workers}")
        if self.connect_timeout_s is not None and self.connect_timeout_s <= 0:
            raise OccDataError(f"the scheduler connect timeout must be > 0, got {self.connect_timeout_s}")
        if self.scheduler is not None and "://" not in self.scheduler and ":" not in self.scheduler:
            raise OccDataError(f"--scheduler {self.scheduler!r}: expected an address such as tcp://host:8786")

    def address(self) -> str | None:
        """The scheduler to reach, or None for an embedded cluster (or in-process run)."""
        return self.scheduler or os.environ.get(SCHEDULER_ENV) or None

    def in_process(self) -> bool:
        return self.address() is None and self.workers == 1


def dask_setup(worker: Any) -> None:
    """Worker preload (runs in each LocalCluster worker process): ignore SIGINT, so a terminal's
    Ctrl-C, which reaches the whole process group, is handled by the client alone. (Thread limits:
    `occdata.runtime.tasks.worker_setup`, applied by every task, also on `--scheduler` workers.)"""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _quiet_dask() -> None:
    for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.worker",
                 "distributed.core", "distributed.comm", "distributed.client", "distributed.batched"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


@contextmanager
def cluster_client(config: ClusterConfig) -> Iterator[Client | None]:
    """A `Client` for `config` (None: run in this process); closes what it started on exit."""
    if config.in_process():
        yield None
        return
    import dask
    from distributed import Client, LocalCluster

    _quiet_dask()
    address = config.address()
    # Workers start with the allocator settings (one arena: see occdata.runtime.allocator).
    # ... and one zarr codec thread each (one task thread per worker: see tasks._limit_zarr_pool).
    spawn_env = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **ALLOCATOR_ENV, **ZARR_POOL_ENV}
    with dask.config.set({"logging.distributed": "critical", "distributed.nanny.pre-spawn-environ": spawn_env,
                          **WORKER_CONFIG}):
        if address is not None:
            try:
                timeout = {} if config.connect_timeout_s is None else {"timeout": config.connect_timeout_s}
                client = Client(address, set_as_default=False, **timeout)
            except (OSError, TimeoutError) as exc:
                raise OccDataError(f"cannot reach the Dask scheduler at {address}: {_reason(exc)}") from None
            try:
                yield client
            finally:
                _close(client)
            return
        try:
            cluster = LocalCluster(n_workers=config.workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=":0", memory_limit=config.memory_limit,
                                   silence_logs=logging.CRITICAL, preload=["occdata.runtime.cluster"])
        except Exception as exc:  # noqa: BLE001 - e.g. a script without `if __name__ == "__main__":`
            raise OccDataError(f"cannot start a Dask LocalCluster of {config.workers} workers: {_reason(exc)} "
                               "(a script that builds must guard its top level with `if __name__ == "
                               "\"__main__\":`, as for multiprocessing)") from None
        client = Client(cluster, set_as_default=False)
        try:
            yield client
        finally:
            _close(client, cluster)


def _close(client: Client, cluster: Any = None) -> None:
    """Close quickly: a running task cannot be interrupted, its worker process is ended instead."""
    try:
        client.close(timeout=5)
    except Exception:  # noqa: BLE001, S110 - the scheduler may be gone already; nothing to report
        pass
    if cluster is not None:
        try:
            cluster.close(timeout=5)
        except Exception:  # noqa: BLE001, S110 - see above
            pass


def _reason(exc: BaseException) -> str:
    # The first argument when it is the message: the default str() of a many-argument exception is a
    # tuple's repr (distributed's TypeError("Could not serialize ...", <the whole graph>)).
    plain = type(exc).__str__ is BaseException.__str__ and len(exc.args) > 1 and isinstance(exc.args[0], str)
    text = exc.args[0] if plain else str(exc)
    text = text.splitlines()[0] if text.strip() else type(exc).__name__
    return text[:200]


class _StopSignals:
    """SIGINT and SIGTERM set a flag (checked between waits); a second SIGINT interrupts at once.
    `extra`: another stop condition checked with the flag (it raises what ends the run)."""

    def __init__(self, extra: Callable[[], None] | None = None) -> None:
        self.signum: int | None = None
        self.extra = extra
        self._prev: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        self.signum = signum
        if signum == signal.SIGINT:
            signal.signal(signal.SIGINT, self._prev.get(signal.SIGINT, signal.default_int_handler))

    def __enter__(self) -> _StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._prev[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, prev in self._prev.items():
            signal.signal(sig, prev)
        self._prev = {}

    def check(self) -> None:
        """The stop check handed to tasks run in this process: raises `Interrupted` once a signal came."""
        if self.signum is not None:
            raise Interrupted(self.signum)
        if self.extra is not None:
            self.extra()


def run_tasks(client: Client | None, tasks: Sequence[T], *, desc: str, unit: str = "task",
              progress: bool = True, on_result: Callable[[T, Any], Sequence[T] | None] | None = None,
              keep: Callable[[T], bool] | None = None, window: int | None = None,
              check: Callable[[], None] | None = None, revoke: Callable[[], None] | None = None,
              total: int | None = None) -> None:
    """Run every task (`client` None: here, one after the other, each given the stop check).

    `on_result(task, result)` runs in this process as each task finishes (in any order) and may
    return follow-up tasks, which run before the remaining ones. `keep(task)`, asked just before a
    task is submitted, drops it when False. `check()`, polled with the stop signals (every 0.25 s,
    and between and inside tasks run here), ends the run with what it raises (a store's lease that
    was lost: `occdata.runtime.lock.StoreLock.check`). The bar counts `task.units` in `unit`s (`total`:
    their sum, when `tasks` makes each task only when indexed, so that no more of them than the window
    ever exist at once: the sequence is read in order, never copied). Raises
    `Interrupted` on Ctrl-C/SIGTERM (queued tasks are cancelled), a task's own exception (the rest
    is cancelled first), or `OccDataError` for anything else on the cluster side: a lost scheduler,
    or an error that is not the connection's, named as what it is (`_not_lost`).

    A run that ends early first calls `revoke()` (the store lock's: the tasks' fence fails from then
    on), cancels the tasks and waits, up to `DRAIN_S`, until no worker still runs one: a task cannot
    be interrupted, so what the caller writes after this returns never races a task's last write.
    """
    if total is None:
        total = sum(t.units for t in tasks)
    bar = tqdm(total=total, desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)
    queue = _Queue(tasks, keep)
    try:
        with _StopSignals(check) as stop:
            if client is None:
                _run_here(queue, stop, bar, on_result)
            else:
                _run_on(client, queue, stop, bar, on_result, window, desc, revoke)
    finally:
        bar.close()


class LazyTasks(Sequence[T]):
    """`make(item)` for each of `items`, made when indexed: handed to `run_tasks` (with `total`), only
    the tasks in flight exist at once, so the client does not hold every task's inputs together."""

    def __init__(self, items: Sequence[Any], make: Callable[[Any], T]) -> None:
        self.items, self.make = items, make

    def __len__(self) -> int:
        return len(self.items)

    @overload
    def __getitem__(self, k: int) -> T: ...
    @overload
    def __getitem__(self, k: slice) -> list[T]: ...

    def __getitem__(self, k: int | slice) -> T | list[T]:
        if isinstance(k, slice):
            return [self.make(item) for item in self.items[k]]
        return self.make(self.items[k])


class _Queue:
    """Tasks still to submit: follow-ups first, then the initial ones in order; `keep` filters."""

    def __init__(self, tasks: Sequence[Any], keep: Callable[[Any], bool] | None) -> None:
        self.urgent: list[Any] = []
        self.tasks, self.next = tasks, 0  # the initial tasks, taken in order by index (made when taken)
        self.keep = keep
        self.seq = 0

    def add(self, follow_ups: Sequence[Any] | None) -> None:
        self.urgent = list(follow_ups or ())[::-1] + self.urgent

    def pop(self) -> tuple[Any, int] | None:
        """The next task and its Dask priority (higher runs first), or None when empty."""
        while self.urgent or self.next < len(self.tasks):
            urgent = bool(self.urgent)
            if urgent:
                task = self.urgent.pop()
            else:
                task, self.next = self.tasks[self.next], self.next + 1
            if self.keep is None or self.keep(task):
                self.seq += 1
                return task, (1 << 30) - self.seq if urgent else -self.seq
        return None


def _run_here(queue: _Queue, stop: _StopSignals, bar: tqdm, on_result: Any) -> None:
    while (item := queue.pop()) is not None:
        stop.check()
        task = item[0]
        worker_setup(None)  # after a task that changed them, e.g. numba's threads (per thread)
        result = task.run(stop.check)
        bar.update(task.units)
        if on_result is not None:
            queue.add(on_result(task, result))
    stop.check()


def _run_on(client: Client, queue: _Queue, stop: _StopSignals, bar: tqdm, on_result: Any,
            window: int | None, desc: str, revoke: Callable[[], None] | None = None) -> None:
    addr = _address(client)  # kept: a closed connection no longer knows it
    if window is None:
        window = max(2, 2 * sum(_nthreads(client, addr).values()))
    running: dict[Future, Any] = {}
    try:
        while True:
            while len(running) < window and (item := queue.pop()) is not None:
                running[_submit(client, item, addr, desc)] = item[0]
            if not running:
                break
            stop.check()
            for f in _wait_some(client, list(running), addr):
                task = running.pop(f)
                result = _result(f, addr, f"a {desc} task ({type(task).__name__})")
                bar.update(task.units)
                if on_result is not None:
                    queue.add(on_result(task, result))
            stop.check()
    finally:
        if running:
            if revoke is not None:
                revoke()
            _cancel(client, list(running))


def _submit(client: Client, item: tuple[Any, int], addr: str, desc: str) -> Future:
    try:
        return client.submit(run_pickled_on_worker, pickle_task(item[0]), pure=False, priority=item[1])
    except (Exception, asyncio.CancelledError) as exc:  # the task is pickled here: its errors come too
        if _is_infrastructure(exc):  # a closed client: nothing of the task's own ran yet
            raise _lost(addr, _reason(exc)) from None
        raise _not_lost(f"submitting a {desc} task ({type(item[0]).__name__})", exc) from exc


def _wait_some(client: Client, futures: list[Future], addr: str) -> set[Future]:
    """The futures that finished within a quarter second (none: check the signals and wait again)."""
    from distributed import wait

    _check_running(client, addr)
    try:
        with client.as_current():
            return set(wait(futures, timeout=0.25, return_when="FIRST_COMPLETED").done)
    except TimeoutError:
        return set()
    except (Exception, asyncio.CancelledError) as exc:  # futures cancelled because the connection broke, ...
        if _is_infrastructure(exc):
            raise _lost(addr, _reason(exc)) from None
        raise _not_lost("waiting for the cluster's results", exc) from exc


def _address(client: Client) -> str:
    try:
        return str(client.scheduler.address)
    except Exception:  # noqa: BLE001 - no connection object any more
        return "?"


def _lost(addr: str, why: str) -> OccDataError:
    """The one message for a scheduler that went away, whichever call noticed it first."""
    return OccDataError(f"lost the Dask scheduler at {addr} ({why}); everything committed so far is kept: "
                        "rerun with --resume")


def _not_lost(where: str, exc: BaseException) -> OccDataError:
    """An error on the cluster path that is not a lost connection (a task or result that does not
    pickle, a bug): what it is and where it was raised. A resume alone would fail the same way."""
    frames = traceback.extract_tb(exc.__traceback__)
    at = f" at {os.path.basename(frames[-1].filename)}:{frames[-1].lineno} in {frames[-1].name}" if frames else ""
    root = exc
    while root.__cause__ is not None:  # distributed wraps a pickling error: "Could not serialize ..." from it
        root = root.__cause__
    cause = f" (from {type(root).__name__}: {_reason(root)})" if root is not exc else ""
    return OccDataError(f"{where} failed: {type(exc).__name__}: {_reason(exc)}{cause}{at}; everything committed "
                        "so far is kept")


def _check_running(client: Client, addr: str) -> None:
    """Fail at once when the client already knows the scheduler is gone (it is reconnecting, or
    closed): a call would wait for the reconnection to time out first (30 s by default)."""
    if client.status != "running":
        raise _lost(addr, str(client.status))


def _nthreads(client: Client, addr: str) -> dict[str, int]:
    _check_running(client, addr)
    try:
        return client.nthreads()
    except (Exception, asyncio.CancelledError) as exc:  # a scheduler gone between connect and submit
        if _is_infrastructure(exc):
            raise _lost(addr, _reason(exc)) from None
        raise _not_lost("asking the scheduler for its workers", exc) from exc


def _is_infrastructure(exc: BaseException) -> bool:
    """A transport or scheduler failure, as distributed raises them: closed connections
    (`distributed.comm.core.CommClosedError`, an OSError; refused or reset connections), timeouts,
    futures cancelled while the client reconnects (`distributed.client.FutureCancelledError`, a
    `concurrent.futures.CancelledError`; `asyncio.CancelledError`), a client already closed
    (`ClosedClientError`), and the bare `OSError("Timed out trying to connect ...")` of
    `distributed.comm.core.connect`. Anything else (TypeError from pickling, RuntimeError from the
    scheduler's graph decoding, a bug) is not. Told apart by type alone: the client's status at
    this instant is a race."""
    from distributed.client import ClosedClientError
    from distributed.comm.core import CommClosedError

    infra = (CommClosedError, ConnectionError, TimeoutError, concurrent.futures.CancelledError,
             asyncio.CancelledError, ClosedClientError)
    return isinstance(exc, infra) or type(exc) is OSError


def _result(f: Future, addr: str, what: str = "a task") -> Any:
    """`f`'s result; a task's own error is re-raised; a lost connection is the lost-scheduler line;
    any other error (`what`: the task, for the message) is named as what it is."""
    from distributed import KilledWorker

    try:
        result = f.result()
    except KilledWorker as exc:
        raise OccDataError(f"a task killed every worker that ran it ({_reason(exc)}); see the worker logs") from None
    except (Exception, asyncio.CancelledError) as exc:  # not the task's own error: that one is a TaskFailed value
        if _is_infrastructure(exc):
            raise _lost(addr, _reason(exc)) from None
        raise _not_lost(what, exc) from exc
    if isinstance(result, TaskFailed):
        result.reraise()
    return result


def _cancel(client: Client, futures: list[Future]) -> None:
    """Cancel `futures`, then wait (up to `DRAIN_S`; a second Ctrl-C ends it) until no worker runs
    one of them any more: Dask marks a running task cancelled at once, but its thread goes on."""
    try:
        client.cancel(futures, force=True)
    except Exception:  # noqa: BLE001, S110 - the scheduler may be gone; closing follows anyway
        return
    keys = {f.key for f in futures}
    deadline = time.monotonic() + DRAIN_S
    while time.monotonic() < deadline:
        try:
            busy = client.run(_active_keys)
        except Exception:  # noqa: BLE001 - no answer: the workers are gone or unreachable, nothing to wait for
            return
        if not keys & {k for ks in busy.values() for k in ks}:
            return
        time.sleep(0.1)


def _active_keys(dask_worker: Any) -> list[Any]:
    """The keys a worker is executing now (run on the worker by `Client.run`)."""
    return list(dask_worker.active_keys)
