"""The image ablation: the backbone's input images replaced by seeded Gaussian noise.

Both training (`noise_images`) and scoring (`score_checkpoint(noise_images=True)`) hook it in, so it
lives with the model rather than in either of them.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

__all__ = ["noise_hook"]


def noise_hook(seed: int) -> Callable[[nn.Module, tuple], tuple]:
    """Forward pre-hook for the backbone: its input images become Gaussian noise (the image ablation)."""
    gen = torch.Generator().manual_seed(seed)

    def hook(module: nn.Module, args: tuple) -> tuple:
        (x,) = args
        return (torch.randn(x.shape, generator=gen).to(x),)

    return hook
