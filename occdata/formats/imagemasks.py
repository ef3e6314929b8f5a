"""The user's own 2D masks: one PNG of class ids per camera image (`occdata labels --image-masks DIR`).

Layout: the mask of the image at `samples/CAM_FRONT/x.jpg` (its path under the dataset root) is
`DIR/samples/CAM_FRONT/x.png`, single channel, 8 bit, the image's size. Ids are Occ3D's (0-16) by
default, any other id meaning "no class here" (`IGNORE`); `--mask-classes FILE` maps a segmenter's
own ids instead: a JSON object `{"<id>": "<Occ3D class name>" | "ignore"}`, unlisted ids ignored.
`occdata synth --image-masks` writes its images' truth in this layout (255: sky).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from occdata.constants import CLASS_NAMES, NUM_CLASSES
from occdata.errors import OccDataError

__all__ = ["IGNORE", "MaskClasses", "load_mask_classes", "mask_path", "read_mask"]

IGNORE = 255  # a pixel whose id maps to no Occ3D class: its points cast no vote
_OCC3D = NUM_CLASSES - 1  # 17 semantic classes, 0..16 (17 is free)


def mask_path(masks_root: Path, image_rel: str | Path) -> Path:
    """Where the mask of the image at `image_rel` (relative to the dataset root) lies under `masks_root`."""
    return Path(masks_root) / Path(image_rel).with_suffix(".png")


@dataclass(frozen=True, eq=False)
class MaskClasses:
    """`lut (256,) uint8`: a mask id -> its Occ3D class, or `IGNORE`; `source`: where the mapping came from."""

    lut: np.ndarray
    source: str = "Occ3D ids"

    def __post_init__(self) -> None:
        if self.lut.shape != (256,) or self.lut.dtype != np.uint8:
            raise ValueError("a mask class table is (256,) uint8")
        if np.any((self.lut >= _OCC3D) & (self.lut != IGNORE)):
            raise ValueError(f"mask classes must be Occ3D classes 0..{_OCC3D - 1} or IGNORE")

    @classmethod
    def occ3d(cls) -> MaskClasses:
        """Ids 0-16 are Occ3D's classes; every other id is ignored."""
        lut = np.full(256, IGNORE, np.uint8)
        lut[:_OCC3D] = np.arange(_OCC3D)
        return cls(lut)


def load_mask_classes(path: Path) -> MaskClasses:
    """`--mask-classes FILE`: `{"<id 0-255>": "<Occ3D class name>" | "ignore"}` (unlisted ids ignored);
    a malformed file fails with one line naming it and the bad entry."""
    try:
        table = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise OccDataError(f"--mask-classes {path}: not a readable JSON file ({exc})") from None
    if not isinstance(table, dict):
        raise OccDataError(f"--mask-classes {path}: expected a JSON object of id -> Occ3D class name")
    names = {n: i for i, n in enumerate(CLASS_NAMES[:_OCC3D])}
    lut = np.full(256, IGNORE, np.uint8)
    for key, name in table.items():
        if not str(key).isdigit() or not 0 <= int(key) <= 255:
            raise OccDataError(f"--mask-classes {path}: id {key!r} is not an integer 0..255")
        if name != "ignore" and name not in names:
            raise OccDataError(f"--mask-classes {path}: id {key}: unknown class {name!r} (an Occ3D class: "
                               f"{', '.join(names)}; or 'ignore')")
        lut[int(key)] = IGNORE if name == "ignore" else names[name]
    return MaskClasses(lut, f"{Path(path).name}: {len(table)} ids mapped")


def read_mask(path: Path, width: int, height: int, classes: MaskClasses) -> np.ndarray:
    """The mask at `path` as Occ3D classes `(height, width) uint8` (`IGNORE` where none); a missing or
    unreadable file, or one of another size, fails with one line naming it."""
    if not Path(path).is_file():
        raise OccDataError(f"image mask {path} is missing (--image-masks needs one PNG per camera image)")
    ids = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if ids is None or ids.ndim != 2 or ids.dtype != np.uint8:
        raise OccDataError(f"image mask {path}: not a single-channel 8-bit PNG of class ids")
    if ids.shape != (height, width):
        raise OccDataError(f"image mask {path} is {ids.shape[1]}x{ids.shape[0]}, its image {width}x{height}")
    return classes.lut[ids]
