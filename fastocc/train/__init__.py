"""`fastocc train`: config, loop, state and run set-up (see docs/training.md); the distributed helpers
are `fastocc.dist`, below both train and infer."""

from fastocc.train.config import ConfigError, TrainConfig, load_config
from fastocc.train.loop import NonFiniteLossError, TrainResult, train

__all__ = ["ConfigError", "NonFiniteLossError", "TrainConfig", "TrainResult", "load_config", "train"]
