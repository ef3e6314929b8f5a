"""Counts in what the commands print: "1 scene", "2 scenes" (never "1 scenes")."""

from __future__ import annotations

__all__ = ["plural"]


def plural(n: int, noun: str, many: str | None = None) -> str:
    """`n` and `noun`, or its plural (`many`, default noun + "s") unless `n` is 1: plural(1, "scene") ==
    "1 scene", plural(3, "sample") == "3 samples", plural(2, "process", "processes")."""
    return f"{n} {noun if n == 1 else many or noun + 's'}"
