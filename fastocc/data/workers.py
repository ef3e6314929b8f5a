"""Loader worker start-up: which start method, and a clear error for scripts that a re-importing
start method would run twice.

What can deadlock a forked worker: zarr runs its IO on an asyncio loop in a background thread; a
forked child that used the parent's loop object waits forever, because the loop's thread does not
exist in the child (tests/test_loader_start_method.py shows it). zarr >= 3.0.3 resets the loop,
its IO thread and its executor in the child (`os.register_at_fork`, zarr PR #2815), which removes
that cause. A plain fork was still not adopted: 30 standalone trials of fork-after-failed-read passed, but
under heavy load a forked-worker pytest run timed out
twice (stack: parent waiting on the workers) and the cause was not pinned down in time, so
workers keep starting from a forkserver (fork-safe by construction: the server forks before any
zarr IO thread exists).

With 'spawn' or 'forkserver' every worker imports the main script again; one that builds its
loader at module level without `if __name__ == "__main__":` used to fail deep inside torch
("DataLoader worker exited unexpectedly"). `check_main_guard` says so upfront, in one line.
"""

from __future__ import annotations

import ast
import contextlib
import multiprocessing
import signal
import sys
import threading
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

from occdata.errors import OccDataError

__all__ = ["check_main_guard", "default_worker_context", "start_iteration"]

T = TypeVar("T")


def default_worker_context() -> Any:
    """A forkserver context with the heavy modules preloaded (cheap worker starts)."""
    import torch

    ctx = torch.multiprocessing.get_context("forkserver")
    # _worker_signals: the server and its workers ignore Ctrl-C (the parent stops them, so no worker
    # tracebacks); listed first because it is cheap to import, which leaves the shortest unprotected window
    ctx.set_forkserver_preload(["fastocc._worker_signals", "torch", "zarr", "cv2", "fastocc.data"])
    return ctx


def _is_main_guard(node: ast.stmt) -> bool:
    if not isinstance(node, ast.If) or not isinstance(node.test, ast.Compare):
        return False
    parts = [node.test.left, *node.test.comparators]
    names = {p.id for p in parts if isinstance(p, ast.Name)}
    consts = {p.value for p in parts if isinstance(p, ast.Constant)}
    return names == {"__name__"} and consts == {"__main__"}


def _unguarded_main_line() -> int | None:
    """Line of the main script's module-level code that (indirectly) calls us, if it is not under
    `if __name__ == "__main__":`; None when called from a function only, or under the guard."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    frame, callee = sys._getframe(1), None
    while frame is not None and not (frame.f_code.co_name == "<module>" and frame.f_globals is vars(main)):
        frame, callee = frame.f_back, frame
    if frame is None or not path:
        return None
    try:
        source = open(path, encoding="utf-8").read()
        tree = ast.parse(source)
    except (OSError, SyntaxError, ValueError):
        return None
    line = frame.f_lineno
    lines = source.splitlines()
    names = callee.f_code.co_qualname.split(".") if callee is not None else []
    if names and (line > len(lines) or not any(n in lines[line - 1] for n in names)):
        return None  # the script on disk was edited since it started: its line numbers no longer say anything
    for node in tree.body:
        if _is_main_guard(node) and node.lineno <= line <= (node.end_lineno or node.lineno):
            return None
    return line


def check_main_guard(context: Any) -> None:
    """Raise `OccDataError` when workers started with `context` would re-run the main script's loader code."""
    method = context.get_start_method() if hasattr(context, "get_start_method") else \
        (context or multiprocessing.get_start_method())
    if method == "fork":
        return
    line = _unguarded_main_line()
    if line is not None:
        script = getattr(sys.modules["__main__"], "__file__", "the main script")
        raise OccDataError(
            f"{script}:{line} creates a data loader with workers at module level, without "
            f"`if __name__ == \"__main__\":`; with the '{method}' start method every worker re-runs the "
            "script. Move that code under the guard (or use num_workers=0)"
        )


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold a Ctrl-C or SIGTERM that arrives inside the block; when the block ends, hand it to the handler
    it would have met (KeyboardInterrupt for Ctrl-C; the CLI's SIGTERM handler raises SystemExit(143)).

    Ctrl-C is held only under Python's default handler, SIGTERM only under a Python handler the caller
    installed (the default action, killing the process, stays as it is). Signals can only be handled
    in the main thread: elsewhere the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: dict[int, Any] = {}
    current = signal.getsignal(signal.SIGINT)
    if current is signal.default_int_handler:
        held[signal.SIGINT] = current
    current = signal.getsignal(signal.SIGTERM)
    if callable(current):
        held[signal.SIGTERM] = current
    caught: list[int] = []
    for sig in held:
        signal.signal(sig, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for sig, handler in held.items():
            signal.signal(sig, handler)
    if caught:
        held[caught[0]](caught[0], None)


def start_iteration(loader: Iterable[T]) -> Iterator[T]:
    """`iter(loader)` with Ctrl-C and SIGTERM held back until the workers have started.

    Interrupted half-way, torch's iterator could not stop the workers it had already started; each
    then found its parent's semaphores gone and printed a traceback of its own (FileNotFoundError),
    or the half-built iterator's own cleanup failed ("no attribute '_workers_status'").
    """
    with _signals_deferred():
        return iter(loader)
