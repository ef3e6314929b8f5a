"""Shared CLI plumbing: turn user-facing errors into one line and a non-zero exit."""

from __future__ import annotations

import functools
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from occdata.errors import OccDataError

__all__ = ["DEFAULT_STORE", "friendly_errors", "local_path"]

DEFAULT_STORE = "data.zarr"  # what `occdata build` writes by default and every store reader opens

F = TypeVar("F", bound=Callable[..., Any])


def friendly_errors(fn: F) -> F:
    """Report `OccDataError`, missing files and bad values as `Error: ...` (exit 1), no traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except OccDataError as exc:
            raise click.ClickException(str(exc)) from None
        except FileNotFoundError as exc:
            raise click.ClickException(f"file not found: {exc.filename or exc}") from None
        except OSError as exc:  # a full disk, a read-only folder, ...: the reason and the file, one line
            where = f": {exc.filename}" if exc.filename else ""
            raise click.ClickException(f"{exc.strerror or exc}{where}") from None

    return wrapper  # type: ignore[return-value]


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
