"""Inference: running a trained network over a store split (shared by `fastocc predict`, `fastocc eval`
and the trainer's validation)."""

from fastocc.infer.evaluate import EvalReport, all_reduce_report, evaluate, reduce_reports
from fastocc.infer.predict import PredictConfig, bev_flip_variants, predict_split

__all__ = [
    "EvalReport",
    "PredictConfig",
    "all_reduce_report",
    "bev_flip_variants",
    "evaluate",
    "predict_split",
    "reduce_reports",
]
