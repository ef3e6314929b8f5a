"""Read-only access to a store: per-sample arrays, images, depth points (no torch)."""

from __future__ import annotations

import urllib.parse
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import zarr

from occdata.errors import OccDataError
from occdata.store.layout import PER_SAMPLE, SCHEMA_NAME, SCHEMA_VERSION, STATE_DONE, token_str

__all__ = ["StoreReader", "open_store", "store_location"]


def store_location(path: str | Path) -> str:
    """A store path or fsspec URL as zarr should get it: `file://` URLs (and the `file:/x` that
    some tools make of them) become plain local paths, so local stores are written with ordinary
    file operations; other URLs (s3://, gs://, memory://, ...) are passed on unchanged."""
    text = str(path)
    if text.startswith("file:"):
        parsed = urllib.parse.urlparse(text)
        if parsed.netloc not in ("", "localhost"):
            raise OccDataError(f"cannot open {text}: only local file:// URLs are supported")
        return urllib.parse.unquote(parsed.path)
    return text


class StoreReader:
    """A thin reader over one store. `root` may be a local path or an fsspec URL."""

    def __init__(self, root: str | Path) -> None:
        self.path = store_location(root)
        try:
            self.group = zarr.open_group(self.path, mode="r")
        except Exception as exc:  # noqa: BLE001 - every failure to open reads the same to a user
            raise OccDataError(f"not a readable occdata store: {self.path} ({type(exc).__name__})") from None
        attrs = dict(self.group.attrs)
        if attrs.get("schema") != SCHEMA_NAME:
            raise OccDataError(f"not an occdata store: {self.path} (no schema attribute)")
        if attrs.get("schema_version") != SCHEMA_VERSION:
            raise OccDataError(
                f"store {self.path} has schema version {attrs.get('schema_version')}, this package reads "
                f"{SCHEMA_VERSION}; rebuild it with this version of occdata"
            )
        self.attrs: dict[str, Any] = attrs
        self.n_samples: int = int(attrs["n_samples"])
        self._cache: dict[str, np.ndarray] = {}

    def array(self, name: str) -> zarr.Array:
        return self.group[name]

    def small(self, name: str) -> np.ndarray:
        """A whole small per-sample array, read once and cached (state, offsets, tokens, poses)."""
        if name not in self._cache:
            self._cache[name] = self.group[name][:]
        return self._cache[name]

    @property
    def state(self) -> np.ndarray:
        return self.group["status/state"][:]

    def done_indices(self) -> np.ndarray:
        return np.flatnonzero(self.state == STATE_DONE)

    def token(self, index: int) -> str:
        return token_str(self.small("sample/token")[index])

    def sample_arrays(self, index: int, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
        """Per-sample arrays (no sample axis) for one sample; all non-status arrays by default."""
        self._check_index(index)
        names = names or tuple(s.name for s in PER_SAMPLE)
        out = {}
        for name in names:
            try:
                out[name] = np.asarray(self.group[name][index])
            except Exception as exc:  # noqa: BLE001 - codec errors surface as many types
                raise OccDataError(
                    f"corrupt store data in {name} for sample {index} ({self.token(index)}): {exc}"
                ) from None
        return out

    def _flat_slice(self, flat: str, offsets_name: str, index: int) -> list[np.ndarray]:
        off = self.small(offsets_name)[index]
        lo = int(off[:, 0].min()) if off[:, 1].any() else 0
        hi = int((off[:, 0] + off[:, 1]).max())
        try:
            data = np.asarray(self.group[flat][lo:hi])
        except Exception as exc:  # noqa: BLE001
            where = f"{flat} for sample {index} ({self.token(index)})"
            raise OccDataError(f"corrupt store data in {where}: {exc}") from None
        return [data[int(s) - lo : int(s) - lo + int(n)] for s, n in off]

    def jpeg_bytes(self, index: int) -> list[bytes]:
        """The 6 stored JPEG streams of a sample, in camera order."""
        self._check_index(index)
        return [a.tobytes() for a in self._flat_slice("images/jpeg", "images/offsets", index)]

    def images(self, index: int, reduce: int = 1) -> list[np.ndarray]:
        """Decoded RGB images `(H, W, 3) uint8`; `reduce` in {1, 2, 4, 8} decodes at 1/reduce scale."""
        flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                8: cv2.IMREAD_REDUCED_COLOR_8}[reduce]
        out = []
        for c, data in enumerate(self.jpeg_bytes(index)):
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flag)
            if img is None:
                raise OccDataError(f"corrupt image data for sample {index} ({self.token(index)}), camera {c}")
            out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        return out

    def depth_points(self, index: int) -> list[np.ndarray]:
        """Per camera `(M_c, 3) float32` (u, v, depth) in original-image pixels."""
        self._check_index(index)
        return [np.asarray(a, dtype=np.float32) for a in self._flat_slice("depth/uvd", "depth/offsets", index)]

    def _check_index(self, index: int) -> None:
        if not 0 <= index < self.n_samples:
            raise OccDataError(f"sample index {index} out of range (store has {self.n_samples} samples)")


def open_store(path: str | Path) -> StoreReader:
    """Open a store for reading: a local path or an fsspec URL (`file:///x.zarr`, `s3://...`)."""
    path = store_location(path)
    if "://" not in path and not Path(path).exists():
        raise OccDataError(f"store not found: {path}")
    return StoreReader(path)
