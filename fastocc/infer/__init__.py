"""Inference: running a trained network over a store split (shared by `fastocc predict`, `fastocc eval`
and the trainer's validation), and `score_checkpoint` for scripts that compare checkpoints."""

from fastocc.infer.evaluate import EvalReport, all_reduce_report, evaluate, reduce_reports
from fastocc.infer.predict import PredictConfig, bev_flip_variants, predict_split
from fastocc.infer.score import report_metrics, score_checkpoint

__all__ = [
    "EvalReport",
    "PredictConfig",
    "all_reduce_report",
    "bev_flip_variants",
    "evaluate",
    "predict_split",
    "reduce_reports",
    "report_metrics",
    "score_checkpoint",
]
