"""FastOcc: camera-only 3D occupancy prediction in PyTorch. `fastocc.Predictor` is the deployment entry point."""

from __future__ import annotations

from typing import Any

__all__ = ["Predictor"]


def __getattr__(name: str) -> Any:
    # lazy: `import fastocc.data` (loader workers) should not pull in the deployment stack
    if name == "Predictor":
        from fastocc.deploy.predictor import Predictor

        return Predictor
    raise AttributeError(f"module 'fastocc' has no attribute {name!r}")
