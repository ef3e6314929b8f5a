"""Occ3D-style occupancy labels generated from LiDAR, 3D boxes and (optionally) lidarseg or 2D masks
(docs/design.md#labels-from-lidar)."""

from occdata.labels.generate import LabelsConfig, LabelsReport, generate_labels
from occdata.labels.options import LabelOptions

__all__ = ["LabelOptions", "LabelsConfig", "LabelsReport", "generate_labels"]
