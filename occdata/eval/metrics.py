"""Occupancy metrics in one import: Occ3D mIoU (`occdata.eval.miou`) and RayIoU (`occdata.eval.rayiou`)."""

from occdata.eval.miou import MIoUAccumulator, MIoUResult, confusion_matrix, confusion_matrix_reference
from occdata.eval.rayiou import (
    RAYIOU_TAUS,
    RayIoUAccumulator,
    RayIoUResult,
    first_hits,
    first_hits_reference,
    lidar_ray_directions,
    ray_counts,
    ray_origins_keyego,
    ray_pitches,
)

__all__ = [
    "RAYIOU_TAUS",
    "MIoUAccumulator",
    "MIoUResult",
    "RayIoUAccumulator",
    "RayIoUResult",
    "confusion_matrix",
    "confusion_matrix_reference",
    "first_hits",
    "first_hits_reference",
    "lidar_ray_directions",
    "ray_counts",
    "ray_origins_keyego",
    "ray_pitches",
]
