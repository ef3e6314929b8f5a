"""`occdata synth`: a synthetic, geometrically exact nuScenes-format world with Occ3D labels."""

from __future__ import annotations

from occdata.synth.pipeline import SynthConfig, synthesize

__all__ = ["SynthConfig", "synthesize"]
