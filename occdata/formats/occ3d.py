"""The Occ3D-nuScenes label file: its layout on disk, reading it (validated) and writing it.

Layout: `<root>/<scene name>/<sample token>/labels.npz` with `semantics`, `mask_lidar`,
`mask_camera`, each `(200, 200, 16) uint8` in key ego (x, y, z; 17 = free; masks 0/1). Some
releases (and `occdata build --gts`) also use the flat `<root>/<sample token>/labels.npz`.
Predictions use the same file with `semantics` (or `pred`), or a flat `<token>.npz`.

OpenOcc v2 files (`openocc_v2/<scene>/<token>/labels.npz`, and `occdata labels --grid openocc-v2`) have the
same path but their own class ids (car 0 ... vegetation 15, free 16; no "others") and a `flow`
`(200, 200, 16, 2)` array; `read_openocc_v2_label` reads them into our ids. A file with `flow` is an
OpenOcc v2 file: `read_label` refuses it rather than read its ids as Occ3D's.

`write_label` is the one writer of these files (`occdata labels` through `occdata.formats.gridfiles`,
`occdata synth`, `fastocc infer`). The readers here validate and map ids; `gridfiles.read_grid_label`
reads a file of any grid as its benchmark's loader does.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from occdata.constants import FREE_LABEL, GRID, NUM_CLASSES
from occdata.errors import OccDataError
from occdata.fileio import npz_bytes, write_atomic
from occdata.formats.gridspec import GRID_PRESETS

__all__ = ["LABEL_FILE", "LABEL_KEYS", "OPENOCC_V2", "label_keys", "list_label_files", "label_path",
           "label_relpaths", "openocc_to_occ3d", "read_label", "read_openocc_v2_label", "read_prediction",
           "read_prediction_flow", "write_label"]

LABEL_FILE = "labels.npz"
LABEL_KEYS = ("semantics", "mask_lidar", "mask_camera")
OPENOCC_V2 = "openocc-v2"  # the label format whose files carry `flow`
_OPENOCC_FREE = GRID_PRESETS[OPENOCC_V2].free_value  # OpenOcc v2's free id, its highest


def openocc_to_occ3d() -> np.ndarray:
    """`(17,) uint8`: OpenOcc v2 class id -> our (Occ3D) id (free 16 -> 17): the openocc-v2 grid's own
    class map, inverted (`occdata.formats.gridfiles.to_occ3d_ids`)."""
    from occdata.formats.gridfiles import to_occ3d_ids

    return to_occ3d_ids(GRID_PRESETS[OPENOCC_V2], np.arange(_OPENOCC_FREE + 1, dtype=np.uint8))


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


def _checked(path: Path, what: str, name: str, a: np.ndarray, top: int,
             shape: tuple[int, ...] = GRID.shape) -> np.ndarray:
    """`a` as `shape` (Occ3D's `(200, 200, 16)` by default) `uint8` with values in 0..top, or one error
    naming file and array."""
    if a.shape != tuple(shape):
        raise OccDataError(f"bad {what} {path}: {name} has shape {a.shape}, expected {tuple(shape)} (x, y, z)")
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
    if "flow" in arrays:
        raise OccDataError(f"bad labels {path}: it has 'flow', so it is an OpenOcc v2 file (its own class ids), "
                           "not Occ3D; a labels tree must hold one format")
    needed = LABEL_KEYS if require_masks else ("semantics",)
    missing = [k for k in needed if k not in arrays]
    if missing:
        raise OccDataError(f"bad labels {path}: missing keys {missing} (has {sorted(arrays)})")
    out = {"semantics": _checked(path, "labels", "semantics", arrays["semantics"], FREE_LABEL)}
    for k in LABEL_KEYS[1:]:
        out[k] = _checked(path, "labels", k, arrays[k], 1) if k in arrays else np.zeros(GRID.shape, np.uint8)
    return out


def label_keys(path: str | Path) -> tuple[str, ...] | None:
    """The array names in an .npz (its zip directory only, no data read), or None if unreadable."""
    try:
        with zipfile.ZipFile(path) as z:
            return tuple(n[:-4] if n.endswith(".npy") else n for n in z.namelist())
    except (OSError, zipfile.BadZipFile, ValueError):
        return None


def _checked_flow(path: Path, what: str, flow: np.ndarray) -> np.ndarray:
    """`flow` as `(200, 200, 16, 2) float32`, finite, or one error naming the file."""
    want = (*GRID.shape, 2)
    if flow.shape != want or flow.dtype.kind != "f":
        raise OccDataError(f"bad {what} {path}: flow has shape {flow.shape} {flow.dtype}, expected {want} float")
    if not np.isfinite(flow).all():
        raise OccDataError(f"bad {what} {path}: flow has {int((~np.isfinite(flow)).sum())} non-finite values")
    return flow.astype(np.float32, copy=False)


def read_openocc_v2_label(path: str | Path) -> dict[str, np.ndarray]:
    """An OpenOcc v2 label file -> `semantics` `(200, 200, 16) uint8` in OUR ids (mapped by class name;
    its free 16 -> 17; it has no "others"), `flow` `(200, 200, 16, 2) float32` (vx, vy) m/s, and
    `mask_lidar` / `mask_camera` (zeros where the file has none, as OpenOcc v2's release). A file
    without `flow` is refused: it is not an OpenOcc v2 file (a labels tree must hold one format)."""
    path = Path(path)
    arrays = _load(path, "labels")
    if "flow" not in arrays or "semantics" not in arrays:
        raise OccDataError(f"bad labels {path}: no {'flow' if 'semantics' in arrays else 'semantics'} array, "
                           f"so it is not an OpenOcc v2 file (has {sorted(arrays)}); a labels tree must hold "
                           "one format")
    sem = _checked(path, "OpenOcc v2 labels", "semantics", arrays["semantics"], _OPENOCC_FREE)
    out = {"semantics": openocc_to_occ3d()[sem], "flow": _checked_flow(path, "labels", arrays["flow"])}
    for k in LABEL_KEYS[1:]:
        out[k] = _checked(path, "labels", k, arrays[k], 1) if k in arrays else np.zeros(GRID.shape, np.uint8)
    return out


def read_prediction_flow(path: str | Path, classes: str = "occ3d",
                         shape: tuple[int, int, int] = GRID.shape) -> tuple[np.ndarray, np.ndarray | None]:
    """A prediction file -> (`(200, 200, 16) uint8` labels in our ids, its `flow` `(200, 200, 16, 2)
    float32` or None when it has none). `classes="openocc-v2"`: its labels are OpenOcc v2 ids (free
    16), mapped to ours by name. `shape`: the labels' grid when not Occ3D's (a store's other grid)."""
    path = Path(path)
    if classes not in ("occ3d", OPENOCC_V2):
        raise OccDataError(f"unknown prediction classes {classes!r} (occ3d or {OPENOCC_V2})")
    arrays = _load(path, "prediction")
    key = "semantics" if "semantics" in arrays else "pred" if "pred" in arrays else None
    if key is None:
        raise OccDataError(f"bad prediction {path}: no 'semantics' or 'pred' array "
                           f"(found: {', '.join(sorted(arrays)) or 'none'})")
    if classes == OPENOCC_V2:
        sem = openocc_to_occ3d()[_checked(path, "prediction", key, arrays[key], _OPENOCC_FREE, shape)]
    else:
        sem = _checked(path, "prediction", key, arrays[key], NUM_CLASSES - 1, shape)
    flow = _checked_flow(path, "prediction", arrays["flow"]) if "flow" in arrays else None
    return sem, flow


def read_prediction(path: str | Path) -> np.ndarray:
    """A prediction file (`semantics` or `pred`) -> `(200, 200, 16) uint8` class labels (17 = free)."""
    return read_prediction_flow(path)[0]


def write_label(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write an Occ3D label or prediction file atomically, with the same bytes for the same arrays."""
    write_atomic(path, npz_bytes(arrays))
