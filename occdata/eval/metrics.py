"""Occupancy metrics in one import: Occ3D mIoU (`occdata.eval.miou`) and RayIoU (`occdata.eval.rayiou`)."""

from occdata.eval import miou, rayiou
from occdata.eval.miou import *  # noqa: F403 - re-exported: this module is the two modules' union
from occdata.eval.rayiou import *  # noqa: F403

__all__ = [*miou.__all__, *rayiou.__all__]
