"""Which split of a store a command runs on when the user names none: `val` when the store has it,
otherwise the store's only split (a one-scene synthetic world has only `train`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from occdata.errors import OccDataError

__all__ = ["DEFAULT_SPLIT", "SplitDefault", "default_split", "store_default_split"]

DEFAULT_SPLIT = "val"


@dataclass(frozen=True)
class SplitDefault:
    """The split chosen for a command, and a line saying why when it is not `val` (else None)."""

    split: str
    note: str | None = None


def default_split(names: Sequence[str], store: str | Path, what: str = "--split") -> SplitDefault:
    """`val` when `names` (the store's splits) holds it, else the only one; several splits without `val`
    (or none) is one `OccDataError` line naming them. `what`: the setting that chooses another split."""
    names = list(names)
    if DEFAULT_SPLIT in names:
        return SplitDefault(DEFAULT_SPLIT)
    if len(names) == 1:
        return SplitDefault(names[0], f"store {store} has no '{DEFAULT_SPLIT}' split: using its only split, "
                                      f"'{names[0]}' ({what} chooses another)")
    if not names:
        raise OccDataError(f"store {store} has no splits (no built samples): nothing to run on")
    raise OccDataError(f"store {store} has no '{DEFAULT_SPLIT}' split and several others ({', '.join(names)}): "
                       f"give {what}")


def store_default_split(store: str | Path, what: str = "--split") -> SplitDefault:
    """`default_split` over the splits recorded in the store's attributes (opens the store)."""
    from occdata.store.reader import open_store

    return default_split(open_store(store).attrs.get("splits", []), store, what)
