"""Run independent, idempotent tasks on Dask distributed (the execution path of `build`, `labels`).

- `ClusterConfig`: `workers` processes of an embedded `LocalCluster` (the default, nothing to start),
  or an existing scheduler (`scheduler="tcp://host:8786"` or `$DASK_SCHEDULER_ADDRESS`). One worker
  without a scheduler runs the tasks in this process (same task functions, no cluster start-up).
- `cluster_client(config)`: a context manager that yields a `distributed.Client` (or None for the
  in-process case) and closes everything it started, also on Ctrl-C or an error.
- `run_tasks(client, fn, tasks, ...)`: submits `fn(task)` for each task (at most a window in flight),
  shows a tqdm bar, hands each task's small result to `on_result` in this process. Ctrl-C or SIGTERM
  cancels what is queued and raises `Interrupted` within seconds; a lost or unreachable scheduler is
  one `OccDataError` line.

A task must be idempotent: Dask reruns it when its worker dies (`distributed.scheduler.allowed-
failures`, default 3), so it writes only what it alone owns (whole chunks, or files it publishes by
rename) and returns only small metadata, never the data. Worker processes of a `LocalCluster` exit
when this process dies (a pipe from the parent, `distributed.process`), and ignore SIGINT (the
terminal's Ctrl-C reaches the whole process group; only the client acts on it).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from tqdm import tqdm

from occdata.errors import OccDataError

if TYPE_CHECKING:  # distributed is imported lazily: `occdata` commands that do not run tasks stay light
    from distributed import Client, Future

__all__ = ["SCHEDULER_ENV", "ClusterConfig", "Interrupted", "check_stop", "cluster_client", "dask_setup",
           "run_tasks"]

SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"
T = TypeVar("T")
R = TypeVar("R")


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
    Ctrl-C, which reaches the whole process group, is handled by the client alone."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:  # one single-threaded task per worker process: no OpenCV thread pool on top (oversubscription)
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass


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
    with dask.config.set({"logging.distributed": "critical"}):
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
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text[:200]


class _StopSignals:
    """SIGINT and SIGTERM set a flag (checked between waits); a second SIGINT interrupts at once."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._prev: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        self.signum = signum
        if signum == signal.SIGINT:
            signal.signal(signal.SIGINT, self._prev.get(signal.SIGINT, signal.default_int_handler))

    def __enter__(self) -> _StopSignals:
        global _ACTIVE
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._prev[sig] = signal.signal(sig, self._handler)
            _ACTIVE = self
        return self

    def __exit__(self, *exc: object) -> None:
        global _ACTIVE
        for sig, prev in self._prev.items():
            signal.signal(sig, prev)
        self._prev = {}
        if _ACTIVE is self:
            _ACTIVE = None

    def check(self) -> None:
        if self.signum is not None:
            raise Interrupted(self.signum)


_ACTIVE: _StopSignals | None = None  # the signals of the `run_tasks` running in this process, if any


def check_stop() -> None:
    """For a long task run in this process (client None): raise `Interrupted` once Ctrl-C or SIGTERM
    has arrived, so it stops within seconds, not at its end; a no-op elsewhere (on a Dask worker).
    Only call it where stopping is safe (the task publishes its results atomically and last)."""
    if _ACTIVE is not None:
        _ACTIVE.check()


def run_tasks(client: Client | None, fn: Callable[[T], R], tasks: Sequence[T], *, desc: str,
              progress: bool = True, units: Callable[[T], int] | None = None,
              on_result: Callable[[T, R], Sequence[T] | None] | None = None,
              keep: Callable[[T], bool] | None = None, window: int | None = None) -> None:
    """Run `fn(task)` for every task (`client` None: here, one after the other).

    `on_result(task, result)` runs in this process as each task finishes (in any order) and may
    return follow-up tasks, which run before the remaining ones. `keep(task)`, asked just before a
    task is submitted, drops it when False. `units(task)` sizes the progress bar (default 1 per
    task). Raises `Interrupted` on Ctrl-C/SIGTERM (queued tasks are cancelled), `OccDataError` when
    the scheduler is lost, or a task's own exception (the rest is cancelled first).
    """
    bar = tqdm(total=sum(units(t) for t in tasks) if units else len(tasks), desc=desc,
               unit="sample" if units else "task", disable=not progress, dynamic_ncols=True)
    queue = _Queue(list(tasks), keep)
    try:
        with _StopSignals() as stop:
            if client is None:
                _run_here(fn, queue, stop, bar, units, on_result)
            else:
                _run_on(client, fn, queue, stop, bar, units, on_result, window)
    finally:
        bar.close()


class _Queue:
    """Tasks still to submit: follow-ups first, then the initial ones in order; `keep` filters."""

    def __init__(self, tasks: list[Any], keep: Callable[[Any], bool] | None) -> None:
        self.urgent: list[Any] = []
        self.rest = tasks[::-1]
        self.keep = keep
        self.seq = 0

    def add(self, follow_ups: Sequence[Any] | None) -> None:
        self.urgent = list(follow_ups or ())[::-1] + self.urgent

    def pop(self) -> tuple[Any, int] | None:
        """The next task and its Dask priority (higher runs first), or None when empty."""
        while self.urgent or self.rest:
            urgent = bool(self.urgent)
            task = (self.urgent or self.rest).pop()
            if self.keep is None or self.keep(task):
                self.seq += 1
                return task, (1 << 30) - self.seq if urgent else -self.seq
        return None


def _run_here(fn: Callable[[T], R], queue: _Queue, stop: _StopSignals, bar: tqdm, units: Any,
              on_result: Any) -> None:
    while (item := queue.pop()) is not None:
        stop.check()
        task = item[0]
        result = fn(task)
        bar.update(units(task) if units else 1)
        if on_result is not None:
            queue.add(on_result(task, result))
    stop.check()


def _run_on(client: Client, fn: Callable[[T], R], queue: _Queue, stop: _StopSignals, bar: tqdm,
            units: Any, on_result: Any, window: int | None) -> None:
    from distributed import wait

    addr = _address(client)  # kept: a closed connection no longer knows it
    if window is None:
        window = max(2, 2 * sum(_nthreads(client, addr).values()))
    running: dict[Future, Any] = {}
    try:
        while True:
            while len(running) < window and (item := queue.pop()) is not None:
                running[client.submit(fn, item[0], pure=False, priority=item[1])] = item[0]
            if not running:
                break
            stop.check()
            if client.status != "running":  # the scheduler went away (the client is reconnecting or closed)
                raise _lost(addr, str(client.status))
            try:
                with client.as_current():
                    done, _ = wait(list(running), timeout=0.25, return_when="FIRST_COMPLETED")
            except TimeoutError:
                done = set()
            except Exception as exc:  # noqa: BLE001 - futures cancelled because the scheduler connection broke
                raise _lost(addr, type(exc).__name__) from None
            for f in done:
                task = running.pop(f)
                result = _result(client, f, addr)
                bar.update(units(task) if units else 1)
                if on_result is not None:
                    queue.add(on_result(task, result))
            stop.check()
    finally:
        if running:
            _cancel(client, list(running))


def _address(client: Client) -> str:
    try:
        return str(client.scheduler.address)
    except Exception:  # noqa: BLE001 - no connection object any more
        return "?"


def _lost(addr: str, why: str) -> OccDataError:
    """The one message for a scheduler that went away, whichever call noticed it first."""
    return OccDataError(f"lost the Dask scheduler at {addr} ({why}); everything committed so far is kept: "
                        "rerun with --resume")


def _nthreads(client: Client, addr: str) -> dict[str, int]:
    try:
        return client.nthreads()
    except Exception as exc:  # noqa: BLE001 - a scheduler gone between connect and submit
        raise _lost(addr, _reason(exc)) from None


def _result(client: Client, f: Future, addr: str) -> Any:
    from distributed import KilledWorker

    try:
        return f.result()
    except KilledWorker as exc:
        raise OccDataError(f"a task killed every worker that ran it ({_reason(exc)}); see the worker logs") from None
    except (OSError, TimeoutError) as exc:
        if client.status in ("running", "connecting") and not _comm_error(exc):
            raise  # the task's own error (a full disk, ...)
        raise _lost(addr, "connection closed" if _comm_error(exc) else _reason(exc)) from None
    except Exception as exc:
        if client.status not in ("running", "connecting") or type(exc).__name__ == "CancelledError":
            raise _lost(addr, f"{client.status}: {_reason(exc)}") from None
        raise


def _comm_error(exc: BaseException) -> bool:
    from distributed.comm.core import CommClosedError

    return isinstance(exc, CommClosedError)


def _cancel(client: Client, futures: list[Future]) -> None:
    try:
        client.cancel(futures, force=True)
    except Exception:  # noqa: BLE001, S110 - the scheduler may be gone; closing follows anyway
        pass
