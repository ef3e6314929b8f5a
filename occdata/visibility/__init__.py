"""Occ3D-style visibility masks (`masks`) and their check against a real Occ3D label (`check`)."""

from occdata.visibility.masks import (
    GROUND_CLASSES,
    MAX_OCCLUDERS,
    camera_mask,
    camera_mask_reference,
    clearance_map,
    clearance_map_reference,
    count_occluders,
    count_occluders_reference,
    lidar_mask,
    lidar_ray_mask,
    lidar_ray_mask_reference,
    object_voxels,
)

__all__ = [
    "GROUND_CLASSES",
    "MAX_OCCLUDERS",
    "camera_mask",
    "camera_mask_reference",
    "clearance_map",
    "clearance_map_reference",
    "count_occluders",
    "count_occluders_reference",
    "lidar_mask",
    "lidar_ray_mask",
    "lidar_ray_mask_reference",
    "object_voxels",
]
