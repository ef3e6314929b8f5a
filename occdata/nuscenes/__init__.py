"""nuScenes-format reading: JSON tables -> frozen keyframe records; LiDAR sweeps."""

from occdata.nuscenes.reader import find_version, load_lidar_points, load_nuscenes, validate_sample
from occdata.nuscenes.records import CameraRecord, LidarRecord, NuScenesDataset, SampleRecord, SceneRecord

__all__ = [
    "CameraRecord",
    "LidarRecord",
    "NuScenesDataset",
    "SampleRecord",
    "SceneRecord",
    "find_version",
    "load_lidar_points",
    "load_nuscenes",
    "validate_sample",
]
