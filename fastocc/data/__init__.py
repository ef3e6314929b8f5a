"""Streaming data for FastOcc: an IterableDataset over an occdata store (see docs/data.md)."""

from fastocc.data.augment import BevAug, BevAugConfig, ImageAug, ImageAugConfig
from fastocc.data.batch import IGNORE_LABEL, Batch, collate
from fastocc.data.dataset import LoaderConfig, StoreDataset, make_loader
from fastocc.data.sample import SampleConfig

__all__ = [
    "IGNORE_LABEL",
    "Batch",
    "BevAug",
    "BevAugConfig",
    "ImageAug",
    "ImageAugConfig",
    "LoaderConfig",
    "SampleConfig",
    "StoreDataset",
    "collate",
    "make_loader",
]
