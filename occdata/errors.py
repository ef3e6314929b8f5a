"""Errors that the CLI turns into one clear line (no traceback)."""

from __future__ import annotations

__all__ = ["OccDataError", "OccDataWarning"]


class OccDataError(Exception):
    """A user-facing problem with input data or options; the message names the file or token."""


class OccDataWarning(UserWarning):
    """A user-facing note (the CLI prints it as one `warning:` line): the work goes on."""
