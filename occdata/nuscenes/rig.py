"""The sensor rig of a nuScenes-format tree, read from its tables (`sensor.json` modality and the
keyframe rows of `sample_data.json`), never assumed.

A rig is which cameras, in which order, and which LiDARs, the first of them the reference LiDAR: its
keyframe timestamp and ego pose define each sample's key-ego frame. nuScenes' six `CAM_*` keep their
model order (`CAMERA_ORDER`, docs/design.md#frames-and-names); other cameras follow by
name. `LIDAR_TOP` is the reference
where there is one, else the first LiDAR by name. A sensor that is not used is named in `left_out`,
one line each, and `occdata scan` / `build` print those lines: nothing is dropped silently.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from occdata.constants import CAMERA_ORDER, LIDAR_CHANNEL
from occdata.errors import OccDataError

__all__ = ["NUSCENES_RIG", "Rig", "RigChoice", "describe_rig", "resolve_rig", "sensor_modalities"]

_USED = ("camera", "lidar")


@dataclass(frozen=True)
class RigChoice:
    """The user's choice (`--cameras`, `--lidars`, `--reference-lidar`); None: every sensor, default
    reference. An explicit list also fixes the order (cameras: the network's camera order)."""

    cameras: tuple[str, ...] | None = None
    lidars: tuple[str, ...] | None = None
    reference_lidar: str | None = None

    def __post_init__(self) -> None:
        for what, names in (("--cameras", self.cameras), ("--lidars", self.lidars)):
            if names is None:
                continue
            if not names:
                raise OccDataError(f"{what} names no sensor")
            twice = sorted({n for n in names if names.count(n) > 1})
            if twice:
                raise OccDataError(f"{what} names {', '.join(twice)} twice")
        if self.reference_lidar is not None and self.lidars is not None and self.reference_lidar not in self.lidars:
            raise OccDataError(
                f"--reference-lidar {self.reference_lidar} is not one of --lidars {','.join(self.lidars)}"
            )

    @classmethod
    def parse(cls, cameras: str | None, lidars: str | None, reference_lidar: str | None) -> RigChoice:
        """From comma-separated option values ("" or None: every sensor)."""

        def names(text: str | None) -> tuple[str, ...] | None:
            return tuple(n.strip() for n in text.split(",") if n.strip()) if text else None

        return cls(names(cameras), names(lidars), reference_lidar or None)


@dataclass(frozen=True)
class Rig:
    """The sensors a dataset is read with: `cameras` in model order, `lidars` with the reference
    LiDAR first; `left_out`: the sensors of the tables that are not used, one line per reason."""

    cameras: tuple[str, ...]
    lidars: tuple[str, ...]
    left_out: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.cameras:
            raise OccDataError("the rig has no camera")
        if not self.lidars:
            raise OccDataError("the rig has no LiDAR")
        if len(set(self.cameras + self.lidars)) != len(self.cameras) + len(self.lidars):
            raise OccDataError(f"the rig names a sensor twice: {self.cameras + self.lidars}")

    @property
    def reference_lidar(self) -> str:
        return self.lidars[0]

    @property
    def channels(self) -> tuple[str, ...]:
        return self.cameras + self.lidars

    @property
    def is_nuscenes(self) -> bool:
        """nuScenes' own rig: the stores of such a tree carry no rig attributes beyond camera_order
        (they stay byte-identical to those built before rigs were read from the tables)."""
        return self.cameras == CAMERA_ORDER and self.lidars == (LIDAR_CHANNEL,)

    def describe(self) -> str:
        """One line, e.g. "7 cameras (CAM_FRONT_LEFT, ...), 3 LiDARs (LIDAR_TOP reference, ...)"."""
        return describe_rig(self.as_attr())

    def as_attr(self) -> dict[str, Any]:
        """The store's `rig` attribute (JSON)."""
        return {"cameras": list(self.cameras), "lidars": list(self.lidars), "reference_lidar": self.reference_lidar}


NUSCENES_RIG = Rig(CAMERA_ORDER, (LIDAR_CHANNEL,))


def describe_rig(attr: Mapping[str, Any]) -> str:
    """One line for a rig attribute (`Rig.as_attr`, or a store's `rig`)."""
    cams, lidars = list(attr.get("cameras", [])), list(attr.get("lidars", []))
    named = [f"{lidars[0]} reference", *lidars[1:]] if lidars else []
    return (f"{len(cams)} camera{'s' * (len(cams) != 1)} ({', '.join(cams)}), "
            f"{len(lidars)} LiDAR{'s' * (len(lidars) != 1)} ({', '.join(named)})")


def sensor_modalities(sensors: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """channel -> modality from `sensor.json` rows; a channel named by two sensors is an `OccDataError`."""
    out: dict[str, str] = {}
    token_of: dict[str, str] = {}
    for tok, row in sensors.items():
        channel, modality = row.get("channel"), row.get("modality")
        if not isinstance(channel, str) or not channel:
            raise OccDataError(f"sensor.json: row {tok!r} has no channel name")
        if channel in out:
            raise OccDataError(f"sensor.json: channel {channel!r} is named by two sensors ({token_of[channel]!r} "
                               f"and {tok!r})")
        out[channel] = str(modality).lower() if isinstance(modality, str) else ""
        token_of[channel] = tok
    return out


def _camera_order(names: Iterable[str]) -> tuple[str, ...]:
    names = set(names)
    return tuple(c for c in CAMERA_ORDER if c in names) + tuple(sorted(names - set(CAMERA_ORDER)))


def resolve_rig(modalities: Mapping[str, str], keyframe_channels: Iterable[str], choice: RigChoice) -> Rig:
    """The rig of a tree: its camera and LiDAR channels (`modalities`, from `sensor_modalities`) that
    have keyframe rows (`keyframe_channels`), narrowed and ordered by `choice`.

    A chosen channel that is not a camera (or LiDAR) of the tables, or has no keyframe row, is an
    `OccDataError` naming what there is."""
    keyed = set(keyframe_channels)
    cams = {c for c, m in modalities.items() if m == "camera" and c in keyed}
    lids = {c for c, m in modalities.items() if m == "lidar" and c in keyed}
    why: dict[str, list[str]] = {}
    for c, m in sorted(modalities.items()):
        if m not in _USED:
            why.setdefault(f"{m or 'no modality'}: not a camera or LiDAR", []).append(c)
        elif c not in keyed:
            why.setdefault(f"{m}: no keyframe rows in sample_data.json", []).append(c)
    cameras = _chosen("--cameras", choice.cameras, cams, "camera") if choice.cameras else _camera_order(cams)
    lidars = _chosen("--lidars", choice.lidars, lids, "LiDAR") if choice.lidars else tuple(sorted(lids))
    if not cameras:
        raise OccDataError("the tables have no camera with keyframe rows (sensor.json modality 'camera')")
    if not lidars:
        raise OccDataError("the tables have no LiDAR with keyframe rows (sensor.json modality 'lidar')")
    for kind, unused, option in (("camera", cams - set(cameras), "--cameras"),
                                 ("lidar", lids - set(lidars), "--lidars")):
        if unused:
            why[f"{kind}: not in {option}"] = sorted(unused)
    left = tuple(f"{', '.join(names)} ({reason})" for reason, names in why.items())
    ref = choice.reference_lidar
    if ref is None:
        ref = LIDAR_CHANNEL if LIDAR_CHANNEL in lidars else (lidars[0] if choice.lidars else sorted(lidars)[0])
    elif ref not in lidars:
        raise OccDataError(f"--reference-lidar {ref} is not a LiDAR of the rig ({', '.join(lidars)})")
    return Rig(cameras, (ref, *(x for x in lidars if x != ref)), left)


def _chosen(option: str, names: tuple[str, ...], available: set[str], kind: str) -> tuple[str, ...]:
    unknown = [n for n in names if n not in available]
    if unknown:
        raise OccDataError(f"{option}: {', '.join(unknown)} is not a {kind} with keyframe rows in the tables "
                           f"(there are: {', '.join(sorted(available)) or 'none'})")
    return names
