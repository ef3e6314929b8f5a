"""Local folders and object stores (fsspec URLs such as s3://bucket/data.zarr) behind one API.

Local paths use ordinary file operations (atomic writes by rename); a URL goes through fsspec,
which reads its options (endpoint, credentials) from the environment (`AWS_ENDPOINT_URL`,
`FSSPEC_S3_ENDPOINT_URL`, ...). On an object store one PUT is atomic by itself: there is no rename,
so "publish" means writing the object whole.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from occdata import fileio
from occdata.errors import OccDataError

__all__ = ["exists", "is_remote", "join", "read_bytes", "remove_tree", "sibling", "write_atomic"]


def is_remote(location: str | Path) -> bool:
    """True for an fsspec URL other than a local file (s3://, gs://, memory://, ...)."""
    text = str(location)
    return "://" in text and not text.startswith("file://")


def _fs(location: str) -> tuple[Any, str]:
    import fsspec

    try:
        return fsspec.core.url_to_fs(location)
    except (ImportError, ValueError) as exc:
        raise OccDataError(f"cannot open {location}: {exc} (s3:// needs `pip install occdata[s3]`)") from None


def join(location: str | Path, *parts: str) -> str:
    text = str(location).rstrip("/")
    return "/".join([text, *parts])


def sibling(location: str | Path, suffix: str) -> str:
    """`<location><suffix>` next to it (`data.zarr` -> `data.zarr.staging`)."""
    return str(location).rstrip("/") + suffix


def exists(location: str | Path) -> bool:
    if not is_remote(location):
        return os.path.lexists(location)
    fs, path = _fs(str(location))
    return bool(fs.exists(path))


def write_atomic(location: str, data: bytes) -> None:
    """Write a whole file/object: a reader sees the old one or the new one, never a part."""
    if not is_remote(location):
        fileio.write_atomic(location, data)  # temporary file, fsync, rename
        return
    fs, path = _fs(location)
    fs.pipe_file(path, data)  # one PUT


def read_bytes(location: str) -> bytes | None:
    """The file's bytes, or None if it does not exist."""
    if not is_remote(location):
        try:
            return Path(location).read_bytes()
        except FileNotFoundError:
            return None
    fs, path = _fs(location)
    try:
        return bytes(fs.cat_file(path))
    except FileNotFoundError:
        return None


def remove_tree(location: str) -> None:
    """Delete a folder/prefix and everything under it; absent is fine."""
    if not is_remote(location):
        shutil.rmtree(location, ignore_errors=True)
        return
    fs, path = _fs(location)
    try:
        fs.rm(path, recursive=True)
    except FileNotFoundError:
        pass
