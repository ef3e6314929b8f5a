"""The allocator settings of build and labels workers (occdata.runtime.allocator): freed sample
buffers stay in the process, so the next sample does not fault fresh pages in."""

from __future__ import annotations

import ctypes.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# 40 MiB: above glibc's largest dynamic mmap threshold (32 MiB), so by default every such buffer is
# a fresh mmap whose pages fault in when written, each time.
_CHURN = """
import ctypes, resource, sys
if sys.argv[1] == "tuned":
    from occdata.runtime.tasks import worker_setup
    worker_setup(1)
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def churn():  # what a sample does to a decoded image: allocate, write, free
    buf = libc.malloc(40 << 20)
    ctypes.memset(buf, 1, 40 << 20)
    libc.free(buf)
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
churn()  # the first one faults in either way
before = faults()
for _ in range(10):
    churn()
print(faults() - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _CHURN, mode], cwd=REPO, capture_output=True, text=True,
                         check=True, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    return int(out.stdout.strip())


@pytest.mark.skipif(not (ctypes.util.find_library("c") or "").startswith("libc.so"), reason="glibc only")
def test_worker_setup_keeps_large_freed_buffers() -> None:
    default, tuned = _faults("default"), _faults("tuned")
    # 10 fresh 40 MiB buffers fault in 102,400 pages of 4 KiB (fewer where the kernel gives huge pages)
    assert default >= 100, default  # the churn the settings remove (the control; ~200 with huge pages)
    assert tuned < default / 10, (tuned, default)


def _worker_env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k.startswith("MALLOC_")}


def test_localcluster_workers_start_with_one_arena() -> None:
    """A Dask worker's task thread takes a heap of its own unless the process starts with one arena;
    Dask's own MALLOC_TRIM_THRESHOLD_ (65536) is replaced, its thread settings are kept."""
    from occdata.runtime.allocator import ALLOCATOR_ENV
    from occdata.runtime.cluster import ClusterConfig, cluster_client

    with cluster_client(ClusterConfig(workers=2)) as client:  # 1 runs in this process
        env = next(iter(client.run(_worker_env).values()))
        threads = next(iter(client.run(lambda: __import__("os").environ.get("OMP_NUM_THREADS")).values()))
    assert env == ALLOCATOR_ENV and env["MALLOC_ARENA_MAX"] == "1"
    assert threads == "1"
