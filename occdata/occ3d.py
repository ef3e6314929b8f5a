"""The Occ3D-nuScenes label file: its layout on disk, reading it (validated) and writing it.

Layout: `<root>/<scene name>/<sample token>/labels.npz` with `semantics`, `mask_lidar`,
`mask_camera`, each `(200, 200, 16) uint8` in key ego (x, y, z; 17 = free; masks 0/1). Some
releases (and `occdata build --gts`) also use the flat `<root>/<sample token>/labels.npz`.
Predictions use the same file with `semantics` (or `pred`), or a flat `<token>.npz`.

Every reader and writer of these files in occdata and fastocc goes through this module.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from occdata.constants import FREE_LABEL, GRID, NUM_CLASSES
from occdata.errors import OccDataError
from occdata.fileio import npz_bytes, write_atomic

__all__ = ["LABEL_FILE", "LABEL_KEYS", "list_label_files", "label_path", "label_relpaths", "read_label",
           "read_prediction", "write_label"]

LABEL_FILE = "labels.npz"
LABEL_KEYS = ("semantics", "mask_lidar", "mask_camera")


def label_path(root: str | Path, scene: str, token: str) -> Path:
    """`<root>/<scene>/<token>/labels.npz`, the Occ3D layout."""
    return Path(root) / scene / token / LABEL_FILE


def label_relpaths(scene: str, token: str) -> tuple[str, str]:
    """The two places a sample's label may be under a labels root: nested (Occ3D) first, then flat."""
    return f"{scene}/{token}/{LABEL_FILE}", f"{token}/{LABEL_FILE}"


def list_label_files(root: str | Path) -> list[Path]:
    """Every `<root>/<scene>/<token>/labels.npz`, sorted (the token is `path.parent.name`)."""
    return sorted(Path(root).glob(f"*/*/{LABEL_FILE}"))


def _load(path: Path, what: str) -> dict[str, np.ndarray]:
    """Every array of an .npz (never unpickles); one `OccDataError` naming the file if unreadable."""
    if path.is_dir():
        raise OccDataError(f"bad {what} {path}: a folder, not an .npz file")
    if not path.exists():
        raise OccDataError(f"bad {what} {path}: file not found")
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise OccDataError(f"bad {what} {path}: not an .npz archive")
        with loaded as npz:
            return {k: np.asarray(npz[k]) for k in npz.files}
    except OccDataError:
        raise
    except (OSError, ValueError, zlib.error, zipfile.BadZipFile, EOFError) as exc:
        raise OccDataError(f"bad {what} {path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None


def _checked(path: Path, what: str, name: str, a: np.ndarray, top: int) -> np.ndarray:
    """`a` as `(200, 200, 16) uint8` with values in 0..top, or one error naming file and array."""
    if a.shape != GRID.shape:
        raise OccDataError(f"bad {what} {path}: {name} has shape {a.shape}, expected {GRID.shape} (x, y, z)")
    if a.dtype.kind not in "biu":
        raise OccDataError(f"bad {what} {path}: {name} has dtype {a.dtype}, expected uint8")
    lo, hi = (int(a.min()), int(a.max())) if a.size else (0, 0)
    if lo < 0 or hi > top:
        bad = int(((a < 0) | (a > top)).sum())
        raise OccDataError(f"bad {what} {path}: {name} has {bad} values outside 0..{top} (min {lo}, max {hi})")
    return a.astype(np.uint8, copy=False)


def read_label(path: str | Path, *, require_masks: bool = False) -> dict[str, np.ndarray]:
    """An Occ3D label file -> `{"semantics", "mask_lidar", "mask_camera"}`, each `(200, 200, 16) uint8`.

    `semantics` is always required (0..17). Without `require_masks`, a missing mask (custom data)
    comes back all zeros, which `occdata visibility` fills in. One `OccDataError` per kind of bad file."""
    path = Path(path)
    arrays = _load(path, "labels")
    needed = LABEL_KEYS if require_masks else ("semantics",)
    missing = [k for k in needed if k not in arrays]
    if missing:
        raise OccDataError(f"bad labels {path}: missing keys {missing} (has {sorted(arrays)})")
    out = {"semantics": _checked(path, "labels", "semantics", arrays["semantics"], FREE_LABEL)}
    for k in LABEL_KEYS[1:]:
        out[k] = _checked(path, "labels", k, arrays[k], 1) if k in arrays else np.zeros(GRID.shape, np.uint8)
    return out


def read_prediction(path: str | Path) -> np.ndarray:
    """A prediction file (`semantics` or `pred`) -> `(200, 200, 16) uint8` class labels (17 = free)."""
    path = Path(path)
    arrays = _load(path, "prediction")
    key = "semantics" if "semantics" in arrays else "pred" if "pred" in arrays else None
    if key is None:
        raise OccDataError(f"bad prediction {path}: no 'semantics' or 'pred' array "
                           f"(found: {', '.join(sorted(arrays)) or 'none'})")
    return _checked(path, "prediction", key, arrays[key], NUM_CLASSES - 1)


def write_label(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write an Occ3D label or prediction file atomically, with the same bytes for the same arrays."""
    write_atomic(path, npz_bytes(arrays))
