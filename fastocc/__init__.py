"""FastOcc: camera-only 3D occupancy prediction in PyTorch. `fastocc.Predictor` is the deployment entry point."""

from __future__ import annotations

import os
import sys
from typing import Any

__all__ = ["Predictor"]

# numba's OpenMP threading layer keeps its threads spinning beside torch's own OpenMP pool: a nano
# training step measured 2-5x slower (CPU time 2.2-4.2 s vs 0.74 s). The workqueue layer does not spin.
# An explicit NUMBA_THREADING_LAYER from the user wins.
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
if "numba" in sys.modules:  # imported before us (e.g. by occdata): its config was read already
    sys.modules["numba"].config.THREADING_LAYER = os.environ["NUMBA_THREADING_LAYER"]


def __getattr__(name: str) -> Any:
    # lazy: `import fastocc.data` (loader workers) should not pull in the deployment stack
    if name == "Predictor":
        from fastocc.deploy.predictor import Predictor

        return Predictor
    raise AttributeError(f"module 'fastocc' has no attribute {name!r}")
