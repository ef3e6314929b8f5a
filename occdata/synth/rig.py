"""The synthetic sensor rig: the calibration of nuScenes scene-0061 (v1.0-mini, vehicle n015).

Values are the calibrated_sensor records of the real fixture (DESIGN §12); a test checks them
against `shared/data/nuscenes-real`. Intrinsics are for 1600x900 and scale with the image size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occdata.constants import CAMERA_ORDER, LIDAR_CHANNEL
from occdata.geometry import transform_from_pose

__all__ = ["CAMERA_TIME_OFFSETS_US", "REFERENCE_SIZE", "RIG", "SensorCalib", "camera_K"]

REFERENCE_SIZE = (1600, 900)  # (W, H) of the calibrated intrinsics


@dataclass(frozen=True)
class SensorCalib:
    """One sensor's calibration: `translation (x, y, z)` m and `rotation_wxyz` (sensor -> ego);
    `intrinsic` ((fx, fy, cx, cy) at 1600x900) for cameras, None for the LiDAR."""

    channel: str
    translation: tuple[float, float, float]
    rotation_wxyz: tuple[float, float, float, float]
    intrinsic: tuple[float, float, float, float] | None

    @property
    def T_ego_from_sensor(self) -> np.ndarray:
        """`(4, 4) float64`."""
        return transform_from_pose(self.translation, self.rotation_wxyz)


RIG: dict[str, SensorCalib] = {
    c.channel: c
    for c in (
        SensorCalib("CAM_FRONT", (1.70079118954, 0.0159456324149, 1.51095763913),
                    (0.4998015430569128, -0.5030316162024876, 0.4997798114386805, -0.49737083824542755),
                    (1266.417203046554, 1266.417203046554, 816.2670197447984, 491.50706579294757)),
        SensorCalib("CAM_FRONT_RIGHT", (1.5508477543, -0.493404796419, 1.49574800619),
                    (0.2060347966337182, -0.2026940577919598, 0.6824507824531167, -0.6713610884174485),
                    (1260.8474446004698, 1260.8474446004698, 807.968244525554, 495.3344268742088)),
        SensorCalib("CAM_BACK_RIGHT", (1.0148780988, -0.480568219723, 1.56239545128),
                    (0.12280980120078765, -0.132400842670559, -0.7004305821388234, 0.690496031265798),
                    (1259.5137405846733, 1259.5137405846733, 807.2529053838625, 501.19579884916527)),
        SensorCalib("CAM_BACK", (0.0283260309358, 0.00345136761476, 1.57910346144),
                    (0.5037872666382278, -0.49740249788611096, -0.4941850223835201, 0.5045496097725578),
                    (809.2209905677063, 809.2209905677063, 829.2196003259838, 481.77842384512485)),
        SensorCalib("CAM_BACK_LEFT", (1.03569100218, 0.484795032713, 1.59097014818),
                    (0.6924185592174665, -0.7031619420114925, -0.11648342771943819, 0.11203317912370753),
                    (1256.7414812095406, 1256.7414812095406, 792.1125740759628, 492.7757465151356)),
        SensorCalib("CAM_FRONT_LEFT", (1.52387798135, 0.494631336551, 1.50932822144),
                    (0.6757265034669446, -0.6736266522251881, 0.21214015046209478, -0.21122827103904068),
                    (1272.5979470598488, 1272.5979470598488, 826.6154927353808, 479.75165386361925)),
        SensorCalib(LIDAR_CHANNEL, (0.943713, 0.0, 1.84023),
                    (0.7077955119163518, -0.006492242056004365, 0.010646214713995808, -0.7063073142877817), None),
    )
}
assert set(RIG) == {*CAMERA_ORDER, LIDAR_CHANNEL}

# Camera trigger times relative to the LiDAR keyframe timestamp (us), as in the real fixture: the
# cameras fire while the spinning LiDAR sweeps past them, 0-45 ms before the sweep's timestamp.
CAMERA_TIME_OFFSETS_US: dict[str, int] = {
    "CAM_FRONT_LEFT": -43107,
    "CAM_FRONT": -35491,
    "CAM_FRONT_RIGHT": -27612,
    "CAM_BACK_RIGHT": -20058,
    "CAM_BACK": -10426,
    "CAM_BACK_LEFT": -528,
}


def camera_K(channel: str, width: int, height: int) -> np.ndarray:
    """Intrinsics `(3, 3) float64` of a rig camera for a `width x height` image (scaled from 1600x900)."""
    calib = RIG[channel]
    assert calib.intrinsic is not None
    fx, fy, cx, cy = calib.intrinsic
    sx, sy = width / REFERENCE_SIZE[0], height / REFERENCE_SIZE[1]
    return np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])
