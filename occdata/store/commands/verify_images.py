"""`occdata verify --images`: decode every stored JPEG and report the damaged ones.

Stores built by this version never hold a JPEG that libjpeg decodes only with a warning (the build
rejects it), but a store built earlier may: its checksums were taken over the damaged bytes, so the
checksum pass cannot see it. This pass decodes each done sample's images at 1/8 scale (the whole
entropy-coded stream is still read) with libjpeg's warnings captured.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2

from occdata.errors import OccDataError
from occdata.sensors.jpeg_check import decode_jpeg_checked
from occdata.store.commands.verify import Problem
from occdata.store.reader import StoreReader

__all__ = ["verify_images"]


def verify_images(reader: StoreReader, progress: Callable[[int], None] | None = None) -> list[Problem]:
    """One `Problem` per damaged image of a done sample (array "images/jpeg", camera named)."""
    problems: list[Problem] = []
    cams = reader.attrs.get("camera_order", [])
    for i in reader.done_indices():
        i = int(i)
        try:
            blobs = reader.jpeg_bytes(i)
        except OccDataError as exc:
            problems.append(Problem(i, reader.token(i), "images/jpeg", str(exc)))
            blobs = []
        for c, data in enumerate(blobs):
            img, warning = decode_jpeg_checked(data, cv2.IMREAD_REDUCED_GRAYSCALE_8)
            if img is None or warning:
                cam = cams[c] if c < len(cams) else f"camera {c}"
                problems.append(Problem(i, reader.token(i), "images/jpeg",
                                        f"{cam}: damaged JPEG ({warning or 'decoder rejected the data'})"))
        if progress:
            progress(1)
    return problems
