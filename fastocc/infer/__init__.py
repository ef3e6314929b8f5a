"""Inference: running a trained network over a store split (shared by `fastocc predict`, `fastocc eval`
and the trainer's validation)."""

from fastocc.infer.predict import PredictConfig, bev_flip_variants, predict_split

__all__ = ["PredictConfig", "bev_flip_variants", "predict_split"]
