"""`fastocc train`: config, loop, state and distributed set-up (see docs/training.md)."""

from fastocc.train.config import ConfigError, TrainConfig, load_config
from fastocc.train.loop import NonFiniteLossError, TrainResult, train

__all__ = ["ConfigError", "NonFiniteLossError", "TrainConfig", "TrainResult", "load_config", "train"]
