"""Loader workers and their forkserver ignore Ctrl-C. Imported by the forkserver only (first in its preload list).

Ctrl-C sends SIGINT to the whole process group. The trainer catches it, saves and shuts its loader
down; a worker that got the signal while still starting died on its own with a traceback on the
terminal. The forkserver gives every child the SIGINT handler that was in place after its preload
imports, so ignoring SIGINT here makes the workers (and the server itself, which else died with
a KeyboardInterrupt traceback when hit during its own start) ignore it. They still stop: the parent
signals them and then terminates stragglers, and torch's watchdog ends a worker whose parent is gone.
It lives outside fastocc.data so that importing it does not import torch first.
"""

from __future__ import annotations

import signal
import sys

__all__: list[str] = []


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


if _in_forkserver():  # importing this module anywhere else changes nothing
    signal.signal(signal.SIGINT, signal.SIG_IGN)
