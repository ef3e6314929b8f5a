"""The viewer's options: one frozen, validated record that `occdata view` fills from its command line."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from occdata.errors import OccDataError

__all__ = ["MASK_CHOICES", "STYLES", "VIEWS", "FrameOptions", "ViewConfig"]

ViewName = Literal["label", "prediction", "side", "error", "speed"]
StyleName = Literal["flat", "cubes"]
VIEWS: dict[str, str] = {  # name -> what the viewer's menu says
    "label": "label",
    "prediction": "prediction",
    "side": "label | prediction",
    "error": "error (right / wrong / missed)",
    "speed": "speed (label coloured by |flow|)",  # stores with flow (OpenOcc v2 labels)
}
STYLES: dict[str, str] = {"flat": "flat (exact class colours)", "cubes": "cubes (shaded)"}
MASK_CHOICES: tuple[str, ...] = ("none", "camera", "lidar", "camera (occdata visibility)", "lidar (occdata visibility)")


@dataclass(frozen=True)
class FrameOptions:
    """How one sample is drawn. `view`: label, prediction, side (label | prediction) or error;
    `mask`: none or a MASK_CHOICES name (voxels outside it are grey, or hidden without `outside_mask`);
    `style`: flat (points in the exact class colours) or cubes (lit boxes); `cameras`: the six frustums
    with their images; `lidar`: the stored depth points lifted to 3D; `hidden`: classes not drawn."""

    view: ViewName = "label"
    mask: str = "none"
    outside_mask: bool = True
    style: StyleName = "flat"
    ego: bool = True
    cameras: bool = True
    lidar: bool = False
    hidden: frozenset[int] = field(default_factory=frozenset)

    def __post_init__(self) -> None:
        if self.view not in VIEWS:
            raise OccDataError(f"unknown view '{self.view}' (one of: {', '.join(VIEWS)})")
        if self.mask not in MASK_CHOICES:
            raise OccDataError(f"unknown mask '{self.mask}' (one of: {', '.join(MASK_CHOICES)})")
        if self.style not in STYLES:
            raise OccDataError(f"unknown style '{self.style}' (one of: {', '.join(STYLES)})")


@dataclass(frozen=True)
class ViewConfig:
    """`occdata view`: the store (path or fsspec URL), an optional prediction folder, which scenes
    (`split`, first `scene`), where to serve (`host`, `port`; 0 = any free port), or instead an `export`
    HTML file of one scene (`seconds_per_keyframe` of playback each). `frame` is the initial drawing."""

    store: str
    pred: Path | None = None
    scene: str | None = None
    split: str | None = None
    host: str = "127.0.0.1"
    port: int = 8080
    export: Path | None = None
    seconds_per_keyframe: float = 0.5
    frame: FrameOptions = field(default_factory=FrameOptions)

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise OccDataError(f"--port {self.port} is not a TCP port (0-65535)")
        if not self.seconds_per_keyframe > 0:
            raise OccDataError(f"seconds per keyframe must be > 0 (got {self.seconds_per_keyframe})")
        if self.pred is None and self.frame.view not in ("label", "speed"):
            raise OccDataError(f"--view {self.frame.view} needs --pred (a prediction folder)")
        if self.export is not None and self.export.suffix.lower() not in (".html", ".htm"):
            raise OccDataError(f"--export {self.export}: the export is one HTML file, name it *.html")

    @property
    def exposed(self) -> bool:
        """True when the server is reachable from other machines (not a loopback address)."""
        if self.host == "localhost":
            return False
        try:
            return not ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return True
