"""Occ3D-style visibility masks (`masks`) and their check against a real Occ3D label (`check`)."""

from occdata.visibility import masks
from occdata.visibility.masks import *  # noqa: F403 - the package's public names are the masks module's

__all__ = list(masks.__all__)
