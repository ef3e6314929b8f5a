"""The synthetic sensor rigs (`occdata synth --rig`): nuScenes, Lyft Level 5 and MAN TruckScenes.

nuscenes (the default): the calibration of nuScenes scene-0061 (v1.0-mini, vehicle n015), the
calibrated_sensor records of the real fixture (DESIGN §12; a test checks them against
`shared/data/nuscenes-real`); intrinsics for 1600x900, scaled with the image size.
lyft: the calibrated_sensor records of the real Lyft Level 5 keyframes (host-a101,
`shared/data/lyft-real`): 7 cameras at 1920x1080, LIDAR_TOP and the two bumper LiDARs.
truckscenes: the channel names of truckscenes-devkit (4 cameras, 6 LiDARs) with plausible mounts on
a truck tractor (the real calibration is not in the devkit), cameras at 1980x943.
The beam patterns of all LiDARs but nuScenes' LIDAR_TOP are plausible, not the real sensors'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occdata.constants import CAMERA_ORDER, LIDAR_CHANNEL
from occdata.geometry import quaternion_wxyz_from_matrix, transform_from_pose

__all__ = ["CAMERA_TIME_OFFSETS_US", "REFERENCE_SIZE", "RIG", "RIGS", "CameraSpec", "LidarSpec", "SensorCalib",
           "SynthRig", "camera_K"]

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


# --- rigs ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraSpec:
    """A rig camera: its calibration (intrinsic at `native_size (W, H)`) and its trigger time relative to
    the reference LiDAR's keyframe timestamp (us)."""

    calib: SensorCalib
    native_size: tuple[int, int]
    time_offset_us: int

    def __post_init__(self) -> None:
        if self.calib.intrinsic is None or min(self.native_size) < 1:
            raise ValueError(f"camera {self.calib.channel}: needs an intrinsic and a positive native size")

    @property
    def channel(self) -> str:
        return self.calib.channel

    def K(self, width: int, height: int) -> np.ndarray:
        """Intrinsics `(3, 3) float64` for a `width x height` image (scaled from the native size)."""
        assert self.calib.intrinsic is not None
        fx, fy, cx, cy = self.calib.intrinsic
        sx, sy = width / self.native_size[0], height / self.native_size[1]
        return np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class LidarSpec:
    """A rig LiDAR: calibration, beam elevations (deg, ring 0 first), azimuth step (deg) of its one-instant
    spin, and its sweep times' offset from the reference LiDAR's (us; 0 for the reference)."""

    calib: SensorCalib
    elevations_deg: tuple[float, ...]
    azimuth_step_deg: float
    time_offset_us: int = 0

    @property
    def channel(self) -> str:
        return self.calib.channel


@dataclass(frozen=True)
class SynthRig:
    """What a synthetic tree of one dataset's rig looks like: sensors (the reference LiDAR first: its
    keyframe timestamp is the sample's), rates, file layout and formats, and table quirks.

    `layout`: "nuscenes" (`samples/`, `sweeps/`), "lyft" (`train_images/`, `train_lidar/`, tables in
    `train_data/`) or "truckscenes" (as nuscenes, with `.pcd` files). `point_format`: "raw5" (float32
    x 5, nuScenes' `.pcd.bin`, Lyft's `.bin`) or "pcd" (binary PCD with x, y, z, intensity and a uint64
    per-point `timestamp`, as truckscenes-devkit reads). `float_timestamps`: microseconds written as JSON
    floats (Lyft); `nan_lidar_size`: NaN width/height on LiDAR rows (Lyft); `ego_motion`: the
    `ego_motion_cabin` / `ego_motion_chassis` tables (TruckScenes); `global_offset`: added to every
    global x, y (TruckScenes' UTM-like coordinates); `tables`: the tables written besides lidarseg;
    `spin_us`: the LiDARs spin over this long, each azimuth sector from the ego pose of its own time,
    and a "pcd" file gives each point that time (an uncompensated cloud); 0: a sweep at one instant.
    """

    name: str
    cameras: tuple[CameraSpec, ...]
    lidars: tuple[LidarSpec, ...]
    keyframe_period_us: int
    sweep_period_us: int
    version: str
    layout: str
    point_format: str
    camera_fileformat: str
    lidar_fileformat: str
    float_timestamps: bool = False
    nan_lidar_size: bool = False
    lidarseg: bool = False
    ego_motion: bool = False
    global_offset: tuple[float, float] = (0.0, 0.0)
    tables: tuple[str, ...] = ()
    spin_us: int = 0

    def __post_init__(self) -> None:
        names = [c.channel for c in self.cameras] + [lidar.channel for lidar in self.lidars]
        if len(set(names)) != len(names) or not self.cameras or not self.lidars:
            raise ValueError(f"rig {self.name}: needs cameras and LiDARs with distinct channels, got {names}")
        if self.keyframe_period_us % self.sweep_period_us:
            raise ValueError(f"rig {self.name}: the LiDAR period must divide the keyframe period")
        if self.layout not in ("nuscenes", "lyft", "truckscenes") or self.point_format not in ("raw5", "pcd"):
            raise ValueError(f"rig {self.name}: unknown layout {self.layout!r} or point format {self.point_format!r}")
        if self.spin_us and (self.point_format != "pcd" or not 0 < self.spin_us <= self.sweep_period_us):
            raise ValueError(f"rig {self.name}: a spin needs per-point times (pcd files) and at most one LiDAR period")

    @property
    def reference(self) -> LidarSpec:
        return self.lidars[0]

    @property
    def native_size(self) -> tuple[int, int]:
        """The cameras' common native (W, H): `--width/--height` default to it."""
        return self.cameras[0].native_size

    @property
    def sweeps_between(self) -> int:
        """Non-keyframe sweeps of each LiDAR between two keyframes."""
        return self.keyframe_period_us // self.sweep_period_us - 1

    def sensor_file(self, scene_name: str, channel: str, t_us: int, key: bool) -> str:
        """A sensor file's path relative to the root (`key`: a keyframe's, else a LiDAR sweep's)."""
        cams = [c.channel for c in self.cameras]
        is_cam = channel in cams
        if self.layout == "lyft":  # flat folders, the sensor's index in the file name, as host-a101's
            if is_cam:
                return f"train_images/{scene_name}_cam{cams.index(channel)}_{t_us}.jpeg"
            return f"train_lidar/{scene_name}_lidar{[x.channel for x in self.lidars].index(channel)}_{t_us}.bin"
        folder = "samples" if key else "sweeps"
        ext = "jpg" if is_cam else ("pcd.bin" if self.point_format == "raw5" else "pcd")
        if self.layout == "truckscenes":
            return f"{folder}/{channel}/{channel}_{t_us}.{ext}"
        return f"{folder}/{channel}/{scene_name}__{channel}__{t_us}.{ext}"


def _look(yaw_deg: float, pitch_deg: float = 0.0) -> tuple[float, float, float, float]:
    """`rotation_wxyz` (camera -> ego) of a camera (x right, y down, z forward) looking at ego yaw
    `yaw_deg`, tilted `pitch_deg` down."""
    y, p = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    forward = np.array([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), -np.sin(p)])
    right = np.array([np.sin(y), -np.cos(y), 0.0])
    down = np.cross(forward, right)
    w, x, yq, z = quaternion_wxyz_from_matrix(np.stack([right, down, forward], axis=1))
    return (w, x, yq, z)


def _yaw(yaw_deg: float) -> tuple[float, float, float, float]:
    """`rotation_wxyz` of a yaw about the ego z axis."""
    h = np.deg2rad(yaw_deg) / 2
    return (float(np.cos(h)), 0.0, 0.0, float(np.sin(h)))


_NUSCENES_TABLES = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
                    "sample_annotation", "sample_data", "scene", "sensor", "visibility")
# nuScenes' LIDAR_TOP: HDL-32E-like, 32 beams, ring 0 = lowest.
_HDL32 = tuple(float(v) for v in np.linspace(-30.67, 10.67, 32))

NUSCENES = SynthRig(
    name="nuscenes",
    cameras=tuple(CameraSpec(RIG[ch], REFERENCE_SIZE, CAMERA_TIME_OFFSETS_US[ch]) for ch in CAMERA_ORDER),
    lidars=(LidarSpec(RIG[LIDAR_CHANNEL], _HDL32, 0.33),),
    keyframe_period_us=500_000, sweep_period_us=50_000,  # 2 Hz keyframes, LIDAR_TOP at 20 Hz
    version="v1.0-mini", layout="nuscenes", point_format="raw5", camera_fileformat="jpg", lidar_fileformat="pcd",
    lidarseg=True, tables=_NUSCENES_TABLES,
)

# Lyft Level 5, host-a101: calibrated_sensor.json of shared/data/lyft-real (fx, fy, cx, cy at 1920x1080).
_LYFT_CAMERAS = (
    ("CAM_FRONT", (1.5039405282244198, -0.02676183592864872, 1.6584901808053665),
     (0.5090416344726354, -0.49422295323980653, 0.4930125688749941, -0.5035463174283287),
     (1109.05239567, 1109.05239567, 957.849065461, 539.672710373), -52398),
    ("CAM_FRONT_RIGHT", (1.2869349480170578, -0.3092550353512263, 1.6839893914336566),
     (-0.19465537600305863, 0.17397929331162632, -0.6816178799126028, 0.6835477714654212),
     (1108.78210897, 1108.78210897, 956.879957389, 536.673966234), -36506),
    ("CAM_BACK_RIGHT", (1.0367992983909404, -0.32137458078567294, 1.66925674671824),
     (-0.17256200786146647, 0.19034914621455828, 0.6851587528493052, -0.6815768770815164),
     (1110.47829059, 1110.47829059, 958.905559894, 536.375069254), -18638),
    ("CAM_BACK", (0.8201327486252449, -0.002437920474569259, 1.6531257722973938),
     (-0.4944743277529699, 0.5037402715904608, 0.5076908453442883, -0.49395433344067297),
     (1112.8384901, 1112.8384901, 958.488205774, 539.540735426), -102398),
    ("CAM_BACK_LEFT", (1.036170645129989, 0.31447962783329736, 1.6505869420762211),
     (-0.6800931780241828, 0.6845869904959692, 0.19499180879571137, -0.17547682511151053),
     (1110.19631475, 1110.19631475, 956.342542632, 538.552500203), -85558),
    ("CAM_FRONT_LEFT", (1.2759992300657645, 0.3217354425926982, 1.6672818053302068),
     (0.686977284209879, -0.6802420406364054, 0.17244107898402378, -0.18867180872950803),
     (1110.7747894, 1110.7747894, 957.955987134, 537.005069228), -69679),
    ("CAM_FRONT_ZOOMED", (1.491748074978969, 0.035422929448341293, 1.5013954883024263),
     (-0.533783350160674, 0.4633916642336896, -0.461074459026301, 0.5364269231158916),
     (3962.24093836, 3962.24093836, 935.362561646, 444.59525683), -51888),
)
LYFT = SynthRig(
    name="lyft",
    cameras=tuple(CameraSpec(SensorCalib(ch, t, q, k), (1920, 1080), dt) for ch, t, q, k, dt in _LYFT_CAMERAS),
    lidars=(
        LidarSpec(SensorCalib("LIDAR_TOP", (1.1970962545449502, 3.680498291456359e-05, 1.8279670539933053),
                              (0.006336712035703651, -0.011344169002788682, 7.18908018654885e-05,
                               0.9999155718069028), None), _HDL32, 0.33),
        # The bumper LiDARs: 16 beams over +-15 deg (plausible), 2 and 4 ms after LIDAR_TOP.
        LidarSpec(SensorCalib("LIDAR_FRONT_LEFT", (3.47289236509973, 0.941603244416182, 0.5427200389242757),
                              (0.01046934325147815, 0.7290775169266195, -0.6842510224225216, 0.011700661422809379),
                              None), tuple(float(v) for v in np.linspace(-15.0, 15.0, 16)), 0.4, 2000),
        LidarSpec(SensorCalib("LIDAR_FRONT_RIGHT", (3.4979440634654573, -0.9496511625133583, 0.5473180779313758),
                              (0.003651633245269522, 0.6883656521848035, 0.7253545303479662, 0.0004469569487147289),
                              None), tuple(float(v) for v in np.linspace(-15.0, 15.0, 16)), 0.4, 4000),
    ),
    keyframe_period_us=200_000, sweep_period_us=200_000,  # every sample_data row a keyframe, 5 Hz
    version="train_data", layout="lyft", point_format="raw5", camera_fileformat="jpeg", lidar_fileformat="bin",
    float_timestamps=True, nan_lidar_size=True, tables=_NUSCENES_TABLES,
)

# TruckScenes: devkit channel names; plausible mounts on a tractor (ego origin at the rear axle, x forward):
# mirror-arm cameras looking diagonally forward and back along the trailer, LiDARs on the cabin's sides,
# roof and rear. 1980x943 images; LiDARs 32 beams (plausible), 10 Hz, each a few ms after LIDAR_LEFT.
_TRUCK_K = (1100.0, 1100.0, 990.0, 471.5)
_TRUCK_BEAMS = tuple(float(v) for v in np.linspace(-25.0, 15.0, 32))
TRUCKSCENES = SynthRig(
    name="truckscenes",
    cameras=tuple(CameraSpec(SensorCalib(ch, t, _look(yaw, 8.0), _TRUCK_K), (1980, 943), dt) for ch, t, yaw, dt in (
        ("CAMERA_LEFT_FRONT", (5.3, 1.35, 2.9), 40.0, -20000),
        ("CAMERA_RIGHT_FRONT", (5.3, -1.35, 2.9), -40.0, -20000),
        ("CAMERA_LEFT_BACK", (5.0, 1.45, 2.9), 160.0, -20000),
        ("CAMERA_RIGHT_BACK", (5.0, -1.45, 2.9), -160.0, -20000),
    )),
    lidars=tuple(LidarSpec(SensorCalib(ch, t, _yaw(yaw), None), _TRUCK_BEAMS, 0.5, dt) for ch, t, yaw, dt in (
        ("LIDAR_LEFT", (5.2, 1.3, 2.3), 90.0, 0),
        ("LIDAR_RIGHT", (5.2, -1.3, 2.3), -90.0, 1000),
        ("LIDAR_TOP_FRONT", (5.6, 0.0, 3.9), 0.0, 2000),
        ("LIDAR_TOP_LEFT", (4.4, 1.1, 3.9), 90.0, 3000),
        ("LIDAR_TOP_RIGHT", (4.4, -1.1, 3.9), -90.0, 4000),
        ("LIDAR_REAR", (-1.4, 0.0, 1.1), 180.0, 5000),
    )),
    keyframe_period_us=500_000, sweep_period_us=100_000,  # 2 Hz keyframes, LiDAR at 10 Hz
    version="v1.0-mini", layout="truckscenes", point_format="pcd", camera_fileformat="jpg", lidar_fileformat="pcd",
    ego_motion=True, global_offset=(690_000.0, 5_335_000.0),  # UTM zone 32U-like, near Munich
    # No map table; a log table although TruckScenes has none (scene.log_token is empty there): our reader
    # resolves scene -> log.
    tables=("attribute", "calibrated_sensor", "category", "ego_motion_cabin", "ego_motion_chassis", "ego_pose",
            "instance", "log", "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility"),
)

RIGS: dict[str, SynthRig] = {r.name: r for r in (NUSCENES, LYFT, TRUCKSCENES)}
