"""The FastOcc network and its baselines, one module per stage (see docs/model.md)."""

from .config import COARSE_GRID, DEPTH_BINS, PRESETS, BackboneConfig, HeadKind, ModelConfig, preset
from .inputs import ModelOutputs, SceneInputs, synthetic_inputs
from .network import FastOcc

__all__ = [
    "COARSE_GRID",
    "DEPTH_BINS",
    "PRESETS",
    "BackboneConfig",
    "FastOcc",
    "HeadKind",
    "ModelConfig",
    "ModelOutputs",
    "SceneInputs",
    "preset",
    "synthetic_inputs",
]
