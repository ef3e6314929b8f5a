"""Small pieces several benchmarks share: where the real data lives, and writing a JSON result."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path
from typing import Any

from benchmarks.provenance import REPO

__all__ = ["CHROMIUM_FLAGS", "OCC3D_LABEL", "REAL_NUSCENES", "REPO", "SHARED_DATA", "emit_json", "write_json"]

# The real nuScenes / Occ3D samples stay outside the repository (../shared/data).
SHARED_DATA = REPO.parent / "shared" / "data"
OCC3D_LABEL = SHARED_DATA / "occ3d-label" / "29796060110c4163b07f06eff4af0753" / "labels.npz"
REAL_NUSCENES = SHARED_DATA / "nuscenes-real"

# Headless Debian chromium with software WebGL, nothing fetched from the network (`occdata view` scripts).
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def write_json(result: Any, path: Path | str, indent: int = 2) -> None:
    """Write `result` as JSON (parents created, trailing newline; non-JSON values via str)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=indent, default=str) + "\n")


def emit_json(result: Any, path: Path | str | None, indent: int = 2) -> None:
    """Print `result` as JSON and, if `path` is given, also write it there."""
    print(json.dumps(result, indent=indent, default=str))
    if path is not None:
        write_json(result, path, indent)


def wait_for_port(port: int, what: str, tries: int = 100) -> None:
    """Return once something listens on 127.0.0.1:`port` (a server started as a subprocess), polling every
    0.1 s; RuntimeError naming `what` after `tries` polls."""
    for _ in range(tries):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"{what} did not start")
