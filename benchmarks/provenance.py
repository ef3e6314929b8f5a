"""The machine / provenance record every benchmark puts under "machine" in its JSON result.

One record, the same keys everywhere, so figures from different scripts and days can be compared and
traced to a commit:

    cpu, cores, cpus_allowed, ram_gib, os, python, versions {numpy, numba, zarr, torch},
    git_commit, git_dirty, command, date (UTC, ISO 8601), loadavg_1min (at the start)
    [+ loadavg_1min_end, set by `finish`] [+ the caller's own fields, e.g. threads or device]

Versions come from the installed distributions' metadata, so recording torch's version does not
import torch (occdata-only benchmarks stay torch-free); a package that is not installed is None.
"""

from __future__ import annotations

import datetime as dt
import importlib.metadata
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

__all__ = ["REPO", "cpu_model", "finish", "git_state", "machine", "ram_gib"]

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("numpy", "numba", "zarr", "torch")


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what `platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def ram_gib() -> float | None:
    """Physical memory in GiB (MemTotal of /proc/meminfo), None where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        pass
    return None


def _version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def git_state(repo: Path = REPO) -> tuple[str | None, bool | None]:
    """(HEAD commit, whether tracked files differ from it) of `repo`; (None, None) outside git."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=True,
                              timeout=30).stdout.strip()

    try:
        return git("rev-parse", "HEAD"), bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return None, None


def machine(**extra: Any) -> dict[str, Any]:
    """The provenance record, taken now (call it when the measurement starts); `extra` fields (a
    benchmark's own settings: threads, device, ...) are added last."""
    commit, dirty = git_state()
    argv = getattr(sys, "orig_argv", sys.argv)  # orig_argv keeps "-m benchmarks.x"
    record: dict[str, Any] = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "cpus_allowed": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "ram_gib": ram_gib(),
        "os": platform.platform(),
        "python": platform.python_version(),
        "versions": {name: _version(name) for name in PACKAGES},
        "git_commit": commit,
        "git_dirty": dirty,
        "command": shlex.join(["python", *argv[1:]]),
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "loadavg_1min": os.getloadavg()[0],
    }
    return record | extra


def finish(record: dict[str, Any]) -> dict[str, Any]:
    """Add the 1-minute load average at the end of the measurement (a loaded machine shows here)."""
    record["loadavg_1min_end"] = os.getloadavg()[0]
    return record
