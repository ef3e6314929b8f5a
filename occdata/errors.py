"""Errors that the CLI turns into one clear line (no traceback)."""

from __future__ import annotations

__all__ = ["OccDataError"]


class OccDataError(Exception):
    """A user-facing problem with input data or options; the message names the file or token."""
