"""The JSON sidecar next to an exported ONNX file: its name and how it is read.

Shared by the exporter (writes it) and the Predictor (reads it); neither imports the other for it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .rig import DeployError

__all__ = ["SIDECAR_FORMAT", "read_sidecar", "sidecar_path"]

SIDECAR_FORMAT = "fastocc.onnx"


def sidecar_path(onnx_path: str | Path) -> Path:
    """`model.onnx` -> `model.json` (the sidecar the Predictor reads)."""
    return Path(onnx_path).with_suffix(".json")


def read_sidecar(path: Path) -> dict[str, Any]:
    """The sidecar of ONNX file `path`, checked to be one of ours (else one `DeployError` line)."""
    side = sidecar_path(path)
    if not side.is_file():
        raise DeployError(f"{path}: no sidecar {side} next to the ONNX file (write both with `fastocc export`)")
    try:
        meta = json.loads(side.read_text())
    except (OSError, ValueError) as exc:
        raise DeployError(f"{side}: unreadable sidecar ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != SIDECAR_FORMAT:
        raise DeployError(f"{side}: not a fastocc ONNX sidecar")
    return meta
