"""Deployment: ONNX export for a fixed rig with a parity check, and the streaming `Predictor` (docs/deploy.md)."""

from .export import ExportConfig, ExportReport, ParityReport, export_model, export_onnx
from .predictor import Predictor
from .rig import DeployError, Rig, load_rig, synthetic_rig

__all__ = [
    "DeployError",
    "ExportConfig",
    "ExportReport",
    "ParityReport",
    "Predictor",
    "Rig",
    "export_model",
    "export_onnx",
    "load_rig",
    "synthetic_rig",
]
