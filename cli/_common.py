"""Shared CLI plumbing: turn user-facing errors into one line and a non-zero exit."""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import urllib.parse
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import click

from occdata.errors import OccDataError

__all__ = ["DEFAULT_STORE", "EXIT_TERMINATED", "exit_on_interrupt", "friendly_errors", "local_path", "stop_on_sigterm"]

EXIT_TERMINATED = 143  # 128 + SIGTERM, as a shell reports a process killed by it

DEFAULT_STORE = "data.zarr"  # what `occdata build` writes by default and every store reader opens

F = TypeVar("F", bound=Callable[..., Any])


def friendly_errors(fn: F) -> F:
    """Report `OccDataError`, missing files and bad values as `Error: ...` (exit 1), no traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except BrokenPipeError:
            _quiet_broken_pipe()
        except OccDataError as exc:
            raise click.ClickException(str(exc)) from None
        except FileNotFoundError as exc:
            raise click.ClickException(f"file not found: {exc.filename or exc}") from None
        except OSError as exc:  # a full disk, a read-only folder, ...: the reason and the file, one line
            where = f": {exc.filename}" if exc.filename else ""
            raise click.ClickException(f"{exc.strerror or exc}{where}") from None

    return wrapper  # type: ignore[return-value]


def _quiet_broken_pipe() -> None:
    """The reader of our output went away (`... | head`): stop quietly, as Unix tools do (status 141 =
    128 + SIGPIPE). stdout goes to /dev/null so that the interpreter's final flush does not complain."""
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    raise SystemExit(141)


def stop_on_sigterm(fn: F) -> F:
    """SIGTERM raises SystemExit(143) in the main thread instead of killing the process outright, so
    `finally` blocks run: the data loader stops its workers and no semaphore is left behind."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        def handler(signum: int, frame: object) -> None:
            raise SystemExit(EXIT_TERMINATED)

        old = signal.signal(signal.SIGTERM, handler)
        try:
            return fn(*args, **kwargs)
        finally:
            signal.signal(signal.SIGTERM, old)

    return wrapper  # type: ignore[return-value]


@contextlib.contextmanager
def exit_on_interrupt(message: str) -> Iterator[None]:
    """Ctrl-C (KeyboardInterrupt) or SIGTERM (occdata.runtime.cluster.Interrupted, a KeyboardInterrupt
    carrying `signum`) inside the block: `message` on stderr and exit status 128 + the signal (130 or
    143, as a shell reports it), no traceback. The work must have kept what it finished."""
    try:
        yield
    except KeyboardInterrupt as exc:
        click.echo(f"\n{message}", err=True)
        raise SystemExit(128 + int(getattr(exc, "signum", signal.SIGINT))) from None


def local_path(value: str | Path, option: str) -> Path:
    """A local path from an option value; a `file://` URL is accepted, another URL is refused with
    one line (the command reads or writes local folders only)."""
    text = str(value)
    if text.startswith("file:"):
        parsed = urllib.parse.urlparse(text)
        if parsed.netloc in ("", "localhost"):
            return Path(urllib.parse.unquote(parsed.path))
    if "://" in text or text.startswith("file:"):
        raise OccDataError(f"{option} must be a local path or a file:// URL, got {text}")
    return Path(text)
