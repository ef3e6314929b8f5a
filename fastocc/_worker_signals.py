"""Loader workers and their forkserver: immune to the job's stop signals, and never outlive their parent.

Imported by the forkserver only (first in its preload list); it lives outside fastocc.data so that
importing it does not import torch first.

Signals. Ctrl-C sends SIGINT to the whole process group, and a cluster scheduler may send SIGTERM
(or a warning signal such as SIGUSR1) to every process of the job. The trainer handles them: it stops
at a step boundary, shuts its loader down and saves. A worker that died of the signal on its own
broke that (a traceback, or "DataLoader worker exited unexpectedly" in the trainer). The forkserver
gives every child the handlers in place after its preload imports, so ignoring the signals here makes
the server ignore them. torch's worker loop then installs a SIGTERM handler of its own (the worker dies
unless the sender is its parent, which is the forkserver, never the trainer), so each worker ignores
the signals again when it starts iterating (`ignore_stop_signals`, called by the dataset). The parent
still stops them (a done event; its last-resort `terminate()` no longer kills a stuck worker, the
parent's exit does, below).

Orphans. If the parent dies without shutting its loader down (SIGKILL, a crash), the forkserver and
the workers used to keep running with parent PID 1 (1.2 GB in one trial, still alive after 100 s).
Now each of them asks the kernel for SIGKILL when its parent dies (Linux `prctl(PR_SET_PDEATHSIG)`):
the trainer's death kills the server, the server's death kills the workers. A worker also runs a
watchdog thread that exits when its parent changes (`os.getppid`), the fallback where prctl is missing.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
import threading
import time

__all__ = ["ignore_stop_signals"]

IGNORED = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)
_PR_SET_PDEATHSIG = 1
WATCHDOG_SECONDS = 1.0


def ignore_stop_signals() -> None:
    """Ignore Ctrl-C, SIGTERM and the warning signals in this process (call in a loader worker's main thread)."""
    for sig in IGNORED:
        signal.signal(sig, signal.SIG_IGN)


def _in_forkserver() -> bool:
    """True while `multiprocessing.forkserver.main` is importing its preload modules."""
    frame = sys._getframe(1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == "main" and code.co_filename.endswith(("multiprocessing/forkserver.py",
                                                                  "multiprocessing\\forkserver.py")):
            return True
        frame = frame.f_back
    return False


def die_with_parent(parent_pid: int) -> None:
    """SIGKILL this process when its parent dies (Linux); exit now if `parent_pid` is already gone."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)


def _watchdog(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(WATCHDOG_SECONDS)
    os._exit(1)


def _after_fork_in_child(server_pid: int) -> None:
    """In each worker the forkserver forks: die with the server, and watch it as a fallback."""
    die_with_parent(server_pid)
    threading.Thread(target=_watchdog, args=(server_pid,), name="fastocc-parent-watchdog", daemon=True).start()


if _in_forkserver():  # importing this module anywhere else changes nothing
    ignore_stop_signals()
    die_with_parent(os.getppid())
    _server = os.getpid()
    os.register_at_fork(after_in_child=lambda: _after_fork_in_child(_server))
