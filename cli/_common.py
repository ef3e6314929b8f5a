"""Shared CLI plumbing: turn every error into one line and a non-zero exit (the traceback only with
`--debug` or `OCCDATA_DEBUG=1`), and `OccDataWarning`s into one `warning:` line each."""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import traceback
import urllib.parse
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import click

from occdata.errors import OccDataError, OccDataWarning

__all__ = ["DEBUG_ENV", "DEFAULT_STORE", "EXIT_TERMINATED", "debug_option", "exit_on_interrupt", "friendly_errors",
           "local_path", "stop_on_sigterm"]

DEBUG_ENV = "OCCDATA_DEBUG"  # "1": print an error's traceback before its line, as --debug does
_DEBUG_KEY = "occdata.debug"

EXIT_TERMINATED = 143  # 128 + SIGTERM, as a shell reports a process killed by it

DEFAULT_STORE = "data.zarr"  # what `occdata build` writes by default and every store reader opens

F = TypeVar("F", bound=Callable[..., Any])


def _set_debug(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value:
        ctx.meta[_DEBUG_KEY] = True  # `meta` is shared with the sub-command's context


debug_option = click.option("--debug", is_flag=True, expose_value=False, is_eager=True, callback=_set_debug,
                            help=f"On an error, print its traceback before the one line (or set {DEBUG_ENV}=1).")


def _debug() -> bool:
    if os.environ.get(DEBUG_ENV, "").strip().lower() in ("1", "true", "yes", "on"):
        return True
    ctx = click.get_current_context(silent=True)
    return bool(ctx is not None and ctx.meta.get(_DEBUG_KEY))


def _one_line(exc: Exception) -> str:
    """The message of an error: ours as it is; an OSError's reason and file; anything else (a bug)
    its type, message and the frame that raised it, with the way to see the traceback."""
    if isinstance(exc, OccDataError):
        return str(exc)
    if isinstance(exc, FileNotFoundError):
        return f"file not found: {exc.filename or exc}"
    if isinstance(exc, OSError):  # a full disk, a read-only folder, ...: the reason and the file
        where = f": {exc.filename}" if exc.filename else ""
        return f"{exc.strerror or exc}{where}"
    text = str(exc).strip().splitlines()
    frames = traceback.extract_tb(exc.__traceback__)
    at = f" at {os.path.basename(frames[-1].filename)}:{frames[-1].lineno} in {frames[-1].name}" if frames else ""
    return (f"unexpected {type(exc).__name__}: {text[0][:300] if text else '(no message)'}{at} (rerun with --debug "
            f"or {DEBUG_ENV}=1 for the traceback)")


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    """Ours as one `warning:` line; any other warning as Python shows it."""
    if issubclass(category, OccDataWarning):
        click.echo(f"warning: {message}", err=True)
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def friendly_errors(fn: F) -> F:
    """Report every error as `Error: ...` (exit 1) and nothing else: `OccDataError`, missing files
    and OS errors by their message, anything else by type, message and where it was raised. With
    `--debug` or `OCCDATA_DEBUG=1` the traceback comes first. Click's own exits pass through."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with warnings.catch_warnings():
                warnings.showwarning = _show_warning
                return fn(*args, **kwargs)
        except BrokenPipeError:
            _quiet_broken_pipe()
        except (click.ClickException, click.exceptions.Exit, click.Abort):
            raise
        except Exception as exc:  # noqa: BLE001 - every error is one line; the traceback only when asked for
            if _debug():
                click.echo("".join(traceback.format_exception(exc)).rstrip(), err=True)
            raise click.ClickException(_one_line(exc)) from None

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
