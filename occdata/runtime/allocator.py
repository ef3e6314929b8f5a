"""glibc's allocator, set for processes that decode and free many large buffers (issue 33).

A build task allocates and frees megabytes per sample: decoded images (1600x900x3), depth maps,
LiDAR sweeps, JPEG and codec buffers. With glibc's defaults those buffers are mmap'ed, or the heap
is trimmed, on every free, and the next sample faults fresh zeroed pages back in: `perf stat` counted
~20 k page faults per sample, and the kernel took 35-45% of the build's CPU. Dask's nanny makes it
worse on purpose (`MALLOC_TRIM_THRESHOLD_=65536`, so its memory monitor sees freed memory go).

`tune_allocator()` keeps freed memory in the process instead, through `mallopt` (glibc only; a
no-op elsewhere). The price: a worker keeps up to `TRIM_THRESHOLD` of free heap after its peak,
which its RSS shows. Applied once per process, by `worker_setup`, so in-process runs,
LocalCluster workers and `--scheduler` workers all get it.

A Dask worker runs its tasks in a pool thread, and glibc gives such a thread its own arena: a chain
of 64 MiB heaps that are unmapped and mapped again as buffers come and go, whatever the thresholds.
One arena for the whole process (`MALLOC_ARENA_MAX=1`) serves the task thread from the main heap;
it must be set before the thread's first allocation, so LocalCluster workers get `ALLOCATOR_ENV` at
spawn (the nanny's `pre-spawn-environ`). On a 240-sample build with 2 workers it took the kernel's
CPU from 7.1 to 2.8 s and the run from 12.8 to 9.8 s. Workers of an existing cluster
(`--scheduler`) should be started with the same environment (docs/scale.md).
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["ALLOCATOR_ENV", "MMAP_THRESHOLD", "TOP_PAD", "TRIM_THRESHOLD", "tune_allocator"]

# mallopt parameters (<malloc.h>)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -2, -3, -8

MMAP_THRESHOLD = 256 << 20  # buffers below this come from the heap, never a fresh mmap
TRIM_THRESHOLD = 1 << 30  # free heap kept before any is handed back to the kernel
TOP_PAD = 64 << 20  # the heap grows in steps of at least this

# The same settings for a process about to start (glibc reads them once, at start-up).
ALLOCATOR_ENV = {"MALLOC_ARENA_MAX": "1", "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD),
                 "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD), "MALLOC_TOP_PAD_": str(TOP_PAD)}

_applied: bool | None = None


def tune_allocator() -> bool:
    """Apply the settings above to this process's glibc allocator, once. True when they are in
    force (now or from an earlier call), False where the C library is not glibc or refused one."""
    global _applied
    if _applied is None:
        # the arena limit binds threads that have not allocated yet (ALLOCATOR_ENV covers the rest)
        _applied = _mallopt({_M_MMAP_THRESHOLD: MMAP_THRESHOLD, _M_TRIM_THRESHOLD: TRIM_THRESHOLD,
                             _M_TOP_PAD: TOP_PAD, _M_ARENA_MAX: 1})
    return _applied


def _mallopt(settings: dict[int, int]) -> bool:
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):  # musl, macOS: no mallopt, nothing to tune
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in settings.items())
