"""Atomic file writes: readers never see a half-written file, a failed write leaves no debris.

The one helper every writer uses (checkpoints, predictions, pictures, sidecars, synthetic worlds):
a unique temporary file in the target folder, fsync, rename. `mkstemp` creates files with mode 0600;
the temporary file is given `0666 & ~umask` first, so the result has the mode `open()` would give
(a teammate in the same group can read a checkpoint when the umask allows it).
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

__all__ = ["TMP_SUFFIX", "atomic_open", "copy_atomic", "current_umask", "is_temp_name", "npz_bytes",
           "remove_stale_temps",
           "replace_synced", "write_atomic"]

TMP_SUFFIX = ".tmp"
# zarr's LocalStore writes `<key>.<uuid4 hex>.partial` and renames it; it removes the file on an
# Exception but not when the process is killed or leaves through SystemExit (our SIGTERM handler).
_ZARR_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial$")


def current_umask() -> int:
    """The process umask, read without changing it where /proc says it (Linux), else set and restored."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_open(path: str | Path) -> Iterator[BinaryIO]:
    """`with atomic_open(p) as f: f.write(...)`: `p` appears complete (fsynced) or not at all.

    On any failure (a full disk, Ctrl-C) the temporary file is removed, the error re-raised and the
    previous `p`, if any, is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def replace_synced(tmp: str | Path, path: str | Path) -> None:
    """Move a finished file that another library wrote (e.g. `torch.onnx.export`) into place like
    `atomic_open` does: fsync it, then rename it over `path`."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically (`atomic_open`)."""
    with atomic_open(path) as f:
        f.write(data)


def copy_atomic(src: str | Path, dst: str | Path) -> None:
    """Copy `src` to `dst` atomically (`atomic_open`), in 4 MiB chunks."""
    with Path(src).open("rb") as fi, atomic_open(dst) as fo:
        while chunk := fi.read(1 << 22):
            fo.write(chunk)


def is_temp_name(key: str) -> bool:
    """Whether a file name (or the last part of a store key) is a temporary: one of `atomic_open`'s
    (`.<name>.<random>.tmp`) or one of zarr LocalStore's (`<name>.<uuid hex>.partial`)."""
    name = key.rsplit("/", 1)[-1]
    return (name.startswith(".") and name.endswith(TMP_SUFFIX)) or bool(_ZARR_PARTIAL.search(name))


def remove_stale_temps(folder: str | Path, recursive: bool = False) -> list[Path]:
    """Delete the temporary files a killed writer leaves (`is_temp_name`: ours and zarr's), in `folder`
    (and below it with `recursive`).

    Only call this while holding the folder's writer lock: another writer's temporaries are live."""
    removed = []
    folder = Path(folder)
    for p in folder.rglob("*") if recursive else folder.glob("*"):
        if is_temp_name(p.name) and p.is_file():
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed .npz archive with fixed zip timestamps (np.savez stamps the current time), so the
    same arrays always give the same bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(info, member.getvalue())
    return buf.getvalue()
