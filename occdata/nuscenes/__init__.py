"""nuScenes-format reading: JSON tables -> frozen keyframe records; LiDAR sweeps; boxes; lidarseg."""

from occdata.nuscenes.annotations import Annotations, BoxRecord, boxes_for_lidar, load_annotations
from occdata.nuscenes.lidarseg import (
    DROP,
    LIDARSEG_NAMES,
    OCC3D_FROM_LIDARSEG,
    lidarseg_index_names,
    load_lidarseg_index,
    occ3d_lut,
    read_lidarseg,
)
from occdata.nuscenes.reader import find_version, load_lidar_points, load_nuscenes, validate_sample
from occdata.nuscenes.records import CameraRecord, LidarRecord, NuScenesDataset, SampleRecord, SceneRecord

__all__ = [
    "DROP",
    "LIDARSEG_NAMES",
    "OCC3D_FROM_LIDARSEG",
    "Annotations",
    "BoxRecord",
    "CameraRecord",
    "LidarRecord",
    "NuScenesDataset",
    "SampleRecord",
    "SceneRecord",
    "boxes_for_lidar",
    "find_version",
    "lidarseg_index_names",
    "load_annotations",
    "load_lidar_points",
    "load_lidarseg_index",
    "load_nuscenes",
    "occ3d_lut",
    "read_lidarseg",
    "validate_sample",
]
