"""Ray origins of a store sample for RayIoU: the bridge from the store to the pure metric code.

`occdata.eval.metrics` is pure algorithm (arrays in, numbers out); reading a scene's poses from a store
lives here.
"""

from __future__ import annotations

import numpy as np

from occdata.errors import OccDataError
from occdata.eval.metrics import ray_origins_keyego
from occdata.formats.gridspec import LabelFrame
from occdata.geometry import invert_rigid, transform_points
from occdata.store.layout import STATE_DONE
from occdata.store.reader import StoreReader

__all__ = ["scene_ray_origins", "store_ray_origins"]


def scene_ray_origins(reader: StoreReader, index: int) -> np.ndarray:
    """`ray_origins_keyego` for store sample `index`, from its scene's committed keyframes.

    Uses `pose/T_global_from_keyego`, `calib/T_ego_from_lidar`, `sample/scene_index` and the scene
    ranges in the store attrs; samples that are not committed (pending, error) are skipped."""
    reader._check_index(index)
    scene = reader.attrs["scenes"][int(reader.small("sample/scene_index")[index])]
    lo = int(scene["first_index"])
    hi = lo + int(scene["num_samples"])
    done = np.flatnonzero(reader.small("status/state")[lo:hi] == STATE_DONE) + lo
    if index not in done:
        raise OccDataError(f"sample {index} ({reader.token(index)}) is not committed in {reader.path}")
    T_g = reader.small("pose/T_global_from_keyego")[done]
    T_el = reader.small("calib/T_ego_from_lidar")[done]
    return ray_origins_keyego(T_g, T_el, int(np.flatnonzero(done == index)[0]))


def store_ray_origins(reader: StoreReader, index: int) -> np.ndarray:
    """`scene_ray_origins` in the frame of the store's label grid, `(n, 3) float64` metres: key ego as
    they are; a LIDAR_TOP-frame grid (SurroundOcc, OpenOccupancy) takes them through the keyframe's
    `inv(calib/T_ego_from_lidar)` (the key ego is the ego pose at that LiDAR timestamp, so the LiDAR frame
    is the key ego moved by the sensor's calibration: exact)."""
    origins = scene_ray_origins(reader, index)
    if reader.grid.frame is not LabelFrame.LIDAR:
        return origins
    T_lidar_from_keyego = invert_rigid(np.asarray(reader.small("calib/T_ego_from_lidar")[index], np.float64))
    return transform_points(T_lidar_from_keyego, origins)
