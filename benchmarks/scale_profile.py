"""Where the build's threads wait: `occdata build` run as a user runs it (the CLI, its own
process, `--workers N`), under a profiler, once per tool and worker count. Not timed figures: a
profiler slows the run. The tools are found on PATH (and beside this Python):

- `strace`: `strace -f -c`, syscall counts and the kernel time in each, summed over every thread
  and process (the LocalCluster's workers too);
- `strace-wall`: `strace -f -c -w`, the wall time spent in each syscall: where threads block
  (futex, poll, read);
- `perf`: `perf stat` of software events (task-clock, context switches, CPU migrations, page
  faults), children included; needs `kernel.perf_event_paranoid` <= 2 (own processes);
- `py-spy`: `py-spy record --subprocesses --idle --threads` (Python stacks, waiting ones included,
  speedscope JSON). Not installed with this project (`pip install py-spy`).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.provenance import REPO

__all__ = ["PROFILERS", "available_profilers", "build_command", "profile_builds", "summary_lines"]

PROFILERS: dict[str, tuple[str, str, Callable[[Path], list[str]]]] = {  # name: (binary, file suffix, prefix)
    "strace": ("strace", "txt", lambda out: ["strace", "-f", "-c", "-o", str(out), "--"]),
    "strace-wall": ("strace", "txt", lambda out: ["strace", "-f", "-c", "-w", "-o", str(out), "--"]),
    "perf": ("perf", "txt", lambda out: ["perf", "stat", "-e", "task-clock,context-switches,cpu-migrations,"
                                         "page-faults", "-o", str(out), "--"]),
    "py-spy": ("py-spy", "speedscope.json",
               lambda out: ["py-spy", "record", "--subprocesses", "--idle", "--threads", "--nonblocking",
                            "--format", "speedscope", "-o", str(out), "--"]),
}


def _which(binary: str) -> str | None:
    return shutil.which(binary, path=os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]))


def available_profilers() -> list[str]:
    """The PROFILERS whose tool is installed here."""
    return [name for name, (binary, _, _) in PROFILERS.items() if _which(binary)]


def build_command(root: Path, gts: Path | None, out: Path, lidar_sweeps: int, block: int, workers: int) -> list[str]:
    """`occdata build` as a user types it."""
    cmd = [sys.executable, "-m", "cli.occdata_cli", "build", "--root", str(root), "--out", str(out),
           "--lidar-sweeps", str(lidar_sweeps), "--block-samples", str(block), "--workers", str(workers),
           "--no-progress"]
    return cmd + (["--gts", str(gts)] if gts is not None else [])


def summary_lines(path: Path, tool: str, limit: int = 14) -> list[str]:
    """The head of a strace summary table (the costliest syscalls) or perf stat's counters."""
    if tool == "py-spy" or not path.is_file():
        return []
    lines = [line.rstrip() for line in path.read_text().splitlines() if line.strip()]
    if tool == "perf":
        return [line for line in lines if not line.lstrip().startswith("#")][:limit]
    return lines[:limit]


def profile_builds(root: Path, gts: Path | None, tmp: Path, dest: Path, tools: list[str], workers: list[int],
                   lidar_sweeps: int, block: int) -> dict[str, Any]:
    """One CLI build per tool and worker count under that tool; the files go to `dest`."""
    dest.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    out: dict[str, Any] = {"tools_found": available_profilers(), "dir": str(dest)}
    for w in workers:
        for tool in tools:
            binary, suffix, prefix = PROFILERS[tool]
            path, store = dest / f"{tool}_w{w}.{suffix}", tmp / f"profile_{tool}_{w}.zarr"
            cmd = prefix(path)
            cmd[0] = _which(binary) or binary
            t0 = time.perf_counter()
            proc = subprocess.run([*cmd, *build_command(root, gts, store, lidar_sweeps, block, w)], cwd=REPO,
                                  env=env, capture_output=True, text=True)
            out[f"{tool}_w{w}"] = {"seconds": time.perf_counter() - t0, "returncode": proc.returncode,
                                   "file": str(path), "summary": summary_lines(path, tool),
                                   "stderr_tail": proc.stderr.strip().splitlines()[-3:] if proc.returncode else []}
            shutil.rmtree(store, ignore_errors=True)
    return out
