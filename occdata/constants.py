"""Fixed facts shared by every stage: classes, colours, the occupancy grid, camera order."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "CAMERA_ORDER",
    "CLASS_COLORS",
    "CLASS_NAMES",
    "EGO_BOX",
    "EGO_SIZE",
    "FREE_LABEL",
    "GRID",
    "LIDAR_CHANNEL",
    "NUM_CLASSES",
    "OccGrid",
]

# Model camera order (docs/design.md#frames-and-names); stored in store attrs so consumers never guess it.
CAMERA_ORDER: tuple[str, ...] = (
    "CAM_FRONT_LEFT",
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_LEFT",
    "CAM_BACK",
    "CAM_BACK_RIGHT",
)
LIDAR_CHANNEL = "LIDAR_TOP"

# The ego car in its own frame (x forward from the rear axle, y left, z up), metres, with a margin:
# LiDAR returns inside it are the car itself (lidarseg's vehicle.ego), dropped with or without
# lidarseg; the pictures and the viewer draw this box. The one ego-car size of the project.
EGO_BOX: tuple[tuple[float, float, float], tuple[float, float, float]] = ((-1.0, -1.1, -0.5), (4.0, 1.1, 2.2))
EGO_SIZE: tuple[float, float, float] = tuple(hi - lo for lo, hi in zip(*EGO_BOX, strict=True))  # length, width, height

CLASS_NAMES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
NUM_CLASSES = len(CLASS_NAMES)  # 18, free included
FREE_LABEL = 17

# RGB per class as in the FastOcc paper's tables; free is never drawn (white placeholder).
CLASS_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),
    (255, 120, 50),
    (255, 192, 203),
    (255, 255, 0),
    (0, 150, 245),
    (0, 255, 255),
    (255, 127, 0),
    (255, 0, 0),
    (255, 240, 150),
    (135, 60, 0),
    (160, 32, 240),
    (255, 0, 255),
    (139, 137, 137),
    (75, 0, 75),
    (150, 240, 80),
    (230, 230, 250),
    (0, 175, 0),
    (255, 255, 255),
)


@dataclass(frozen=True)
class OccGrid:
    """An axis-aligned voxel grid in the key-ego frame (x forward, y left, z up), metres."""

    lower: tuple[float, float, float] = (-40.0, -40.0, -1.0)
    upper: tuple[float, float, float] = (40.0, 40.0, 5.4)
    voxel_size: float = 0.4

    @property
    def shape(self) -> tuple[int, int, int]:
        """(X, Y, Z) voxel counts."""
        return tuple(  # type: ignore[return-value]
            round((hi - lo) / self.voxel_size) for lo, hi in zip(self.lower, self.upper, strict=True)
        )

    def voxel_centers(self) -> np.ndarray:
        """Centres of all voxels in key ego, `(X, Y, Z, 3) float32`, axis order (x, y, z)."""
        axes = [
            lo + self.voxel_size * (np.arange(n, dtype=np.float64) + 0.5)
            for lo, n in zip(self.lower, self.shape, strict=True)
        ]
        gx, gy, gz = np.meshgrid(*axes, indexing="ij")
        return np.stack([gx, gy, gz], axis=-1).astype(np.float32)

    def index_of(self, points_ego: np.ndarray) -> np.ndarray:
        """Integer voxel indices `(N, 3) int64` of points `(N, 3)` (floor; may be out of range)."""
        lower = np.asarray(self.lower, dtype=np.float64)
        return np.floor((np.asarray(points_ego, dtype=np.float64) - lower) / self.voxel_size).astype(np.int64)


GRID = OccGrid()
