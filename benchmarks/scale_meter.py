"""The accounting of one timed run for benchmarks.bench_scale. Linux only (/proc).

- wall time, and the units the run did (samples, keyframes);
- CPU seconds, user and kernel, of this process (the client: tables, planning, the embedded
  scheduler and nannies, `on_result`; with one worker also every task) and of each Dask worker,
  from `getrusage(RUSAGE_SELF)` taken before and after the run in every process (`client.run`).
  RUSAGE_CHILDREN is no use here: a LocalCluster's worker processes are children of this process,
  but count there only once reaped, at the cluster's close, with start-up and the warm-up run in;
- context switches (voluntary: a thread blocked, e.g. on a futex; involuntary: preempted), bytes
  passed to write(2) (`wchar` of /proc/<pid>/io: files and pipes, not socket sends), threads;
- the time from the start to the first task running: Dask's task stream (the first `compute`
  start on a worker); in this process, the first `run_tasks` call (its first task starts at
  once), with the client's CPU until then;
- the workers' busy share: their tasks' compute time over (wall time x workers);
- inside the tasks (`task_probe`: each build or labels task's `run` wrapped in every process that runs
  tasks): the process's CPU during each task, user and kernel, and the task thread's own share of
  it (the rest: zarr's codec and IO threads, Dask's threads meanwhile), against each process's whole
  CPU over the run: what a worker spends outside its tasks (receiving and unpickling tasks, Dask's
  event loop, results) is the difference.
"""

from __future__ import annotations

import importlib
import os
import resource
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

__all__ = ["TASK_ENTRIES", "first_call", "measure", "process_cpu", "task_probe", "taken_tasks", "usage"]

# Where `build` and `labels` hand their tasks to the runtime: patched to note the first call.
TASK_ENTRIES = (("occdata.store.build", "run_tasks"), ("occdata.labels.generate", "run_tasks"))
_SUMMED = ("user", "sys", "vcsw", "ivcsw", "wchar")


def _proc_value(file: str, key: str) -> int:
    """`key: N` from /proc/self/<file> (0 where unreadable)."""
    try:
        with open(f"/proc/self/{file}") as f:
            return next((int(line.split()[1]) for line in f if line.startswith(key + ":")), 0)
    except OSError:
        return 0


def usage() -> dict[str, float]:
    """This process so far: CPU seconds (user, sys), context switches (voluntary, involuntary),
    bytes written (wchar), threads now, peak RSS (MiB). Also run on the workers (`client.run`)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return {"user": ru.ru_utime, "sys": ru.ru_stime, "vcsw": ru.ru_nvcsw, "ivcsw": ru.ru_nivcsw,
            "wchar": _proc_value("io", "wchar"), "threads": _proc_value("status", "Threads"),
            "maxrss_mib": ru.ru_maxrss / 1024}


_TASK_CLASSES = (("occdata.store.blocks", "ConvertJob"), ("occdata.labels.generate", "SceneJob"))
_taken: list[tuple[int, float, float, float, float]] = []  # per task: units, user, sys, thread CPU, wall


def _probed(run: Callable[..., Any]) -> Callable[..., Any]:
    def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
        r0, th0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.thread_time(), time.perf_counter()
        try:
            return run(self, *args, **kwargs)
        finally:
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            _taken.append((int(self.units), r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime,
                           time.thread_time() - th0, time.perf_counter() - w0))

    timed.original = run  # type: ignore[attr-defined]
    return timed


def task_probe() -> None:
    """From now on, note each build / labels task's CPU in this process (`taken_tasks` returns them).
    Patches the task classes' `run`, which unpickled tasks share; idempotent."""
    _taken.clear()
    for module_name, name in _TASK_CLASSES:
        cls = getattr(importlib.import_module(module_name), name)
        if not hasattr(cls.run, "original"):
            cls.run = _probed(cls.run)


def taken_tasks() -> list[tuple[int, float, float, float, float]]:
    """The tasks noted since `task_probe` (units, user, sys, thread CPU, wall seconds); the probe is removed."""
    for module_name, name in _TASK_CLASSES:
        cls = getattr(importlib.import_module(module_name), name)
        if hasattr(cls.run, "original"):
            cls.run = cls.run.original
    out = list(_taken)
    _taken.clear()
    return out


def process_cpu(pid: int) -> dict[str, float]:
    """Another process's CPU seconds so far, user and sys (/proc/<pid>/stat), e.g. the S3 server's."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return {"user": int(fields[11]) / tick, "sys": int(fields[12]) / tick}


def _delta(a: dict[str, float], b: dict[str, float], keys: tuple[str, ...] = _SUMMED) -> dict[str, float]:
    return {k: b[k] - a[k] for k in keys if k in a and k in b}


@contextmanager
def first_call(entries: tuple[tuple[str, str], ...] = TASK_ENTRIES) -> Iterator[dict[str, Any]]:
    """While open, each `module.name` in `entries` notes the wall time and `usage()` of its first call
    (of any of them) in the yielded dict (keys `time`, `usage`; empty if none was called)."""
    seen: dict[str, Any] = {}
    patched = []

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        def noted(*args: Any, **kwargs: Any) -> Any:
            if not seen:
                seen.update(time=time.time(), usage=usage())
            return fn(*args, **kwargs)
        return noted

    for module_name, name in entries:
        module = importlib.import_module(module_name)
        patched.append((module, name, getattr(module, name)))
        setattr(module, name, wrap(getattr(module, name)))
    try:
        yield seen
    finally:
        for module, name, original in patched:
            setattr(module, name, original)


def _workers_usage(client: Any) -> dict[str, dict[str, float]]:
    return {} if client is None else client.run(usage)


def measure(run: Callable[[], int], client: Any = None, server_pid: int | None = None) -> dict[str, Any]:
    """Run `run` once (it returns the units it did), timed, with the accounting of the module
    docstring. `client`: the Dask client the run uses (None: it runs in this process);
    `server_pid`: a server process whose CPU to count apart (the S3 server)."""
    w0 = _workers_usage(client)
    task_probe()
    if client is not None:
        client.run(task_probe)
    s0 = process_cpu(server_pid) if server_pid else None
    with ExitStack() as stack:
        first = stack.enter_context(first_call())
        stream = None
        if client is not None:
            from distributed import get_task_stream

            stream = stack.enter_context(get_task_stream(client=client))
        c0, start, t0 = usage(), time.time(), time.perf_counter()
        units = run()
        seconds = time.perf_counter() - t0
        c1 = usage()
        s1 = process_cpu(server_pid) if server_pid else None
    w1 = _workers_usage(client)
    tasks = taken_tasks() + [t for per in (client.run(taken_tasks) if client is not None else {}).values() for t in per]
    workers = {a: _delta(w0[a], w1[a]) for a in w1 if a in w0}
    rec = _cpu_summary(units, seconds, _delta(c0, c1), workers)
    rec["in_tasks"] = _in_tasks(tasks, units, _delta(c0, c1) if client is None else
                                {k: sum(d[k] for d in workers.values()) for k in ("user", "sys")})
    rec["threads"] = {"client": c1["threads"], "workers": sorted(u["threads"] for u in w1.values())}
    if w1:
        rec["worker_peak_rss_mib"] = sorted(round(u["maxrss_mib"], 1) for u in w1.values())
    rec |= _first_task(start, seconds, c0, first, stream)
    if stream is not None:
        rec |= _busy(stream.data, seconds, len(w1))
    if s0 is not None and s1 is not None:
        rec["server_cpu_s_per_unit"] = {k: v / units for k, v in _delta(s0, s1, ("user", "sys")).items()}
    return rec


def _cpu_summary(units: int, seconds: float, client: dict[str, float],
                 workers: dict[str, dict[str, float]]) -> dict[str, Any]:
    """Rates and CPU per unit from the client's and the workers' deltas."""
    w = {k: sum(d[k] for d in workers.values()) for k in _SUMMED}
    user, kernel = client["user"] + w["user"], client["sys"] + w["sys"]
    cpu = max(user + kernel, 1e-9)
    return {
        "seconds": seconds, "units": units, "units_per_s": units / seconds,
        "cpu_s_per_unit": {"user": user / units, "sys": kernel / units},
        "kernel_share": kernel / cpu, "client_share": (client["user"] + client["sys"]) / cpu,
        "cores_busy": cpu / seconds,
        "cpu_s": {"client": {"user": client["user"], "sys": client["sys"]},
                  "workers": {"user": w["user"], "sys": w["sys"]}},
        "context_switches_per_unit": {"voluntary": (client["vcsw"] + w["vcsw"]) / units,
                                      "involuntary": (client["ivcsw"] + w["ivcsw"]) / units},
        "written_bytes_per_unit": (client["wchar"] + w["wchar"]) / units,
    }


def _in_tasks(tasks: list[tuple[int, float, float, float, float]], units: int,
              runners: dict[str, float]) -> dict[str, Any]:
    """CPU inside the tasks against the whole CPU of the processes that ran them (`runners`: user and
    sys of the workers, or of this process when it ran the tasks): per unit, and what is left outside."""
    user, kernel = sum(t[1] for t in tasks), sum(t[2] for t in tasks)
    thread, wall = sum(t[3] for t in tasks), sum(t[4] for t in tasks)
    whole = runners["user"] + runners["sys"]
    done = max(sum(t[0] for t in tasks), 1)
    return {"tasks": len(tasks), "units": done,
            "cpu_s_per_unit": {"user": user / done, "sys": kernel / done},
            "task_thread_cpu_s_per_unit": thread / done,
            "other_threads_cpu_share": (user + kernel - thread) / max(user + kernel, 1e-9),
            "task_wall_s_per_unit": wall / done,
            "task_cores_busy": (user + kernel) / max(wall, 1e-9),
            "runner_cpu_s": whole, "outside_tasks_cpu_s": whole - user - kernel,
            "outside_tasks_cpu_s_per_unit": (whole - user - kernel) / max(units, 1)}


def _first_task(start: float, seconds: float, c0: dict[str, float], first: dict[str, Any],
                stream: Any) -> dict[str, Any]:
    """Seconds from the start to the first `run_tasks` call and to the first task running, the
    client's CPU until the first call, and the start-up's share of the run."""
    out: dict[str, Any] = {}
    if first:
        out["first_submit_s"] = first["time"] - start
        spent = _delta(c0, first["usage"], ("user", "sys"))
        out["client_cpu_before_first_task_s"] = spent["user"] + spent["sys"]
    starts = [ss["start"] for task in (stream.data if stream is not None else ())
              for ss in task.get("startstops", ()) if ss.get("action") == "compute"]
    first_task = min(starts) - start if starts else out.get("first_submit_s")
    if first_task is not None:
        out["first_task_s"] = first_task
        out["startup_share"] = first_task / seconds
    return out


def _busy(tasks: list[dict[str, Any]], seconds: float, workers: int) -> dict[str, Any]:
    """The tasks' compute time (Dask's task stream) and the workers' busy share."""
    compute = sum(ss["stop"] - ss["start"] for task in tasks for ss in task.get("startstops", ())
                  if ss.get("action") == "compute")
    return {"tasks": len(tasks), "task_compute_s": compute,
            "worker_busy_share": compute / (seconds * workers) if workers else None}
