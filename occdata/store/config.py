"""`BuildConfig`: every option of `occdata build`, validated once, where the labels come from."""

from __future__ import annotations

import enum
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from occdata.errors import OccDataError
from occdata.formats.gridspec import GridSpec
from occdata.nuscenes.reader import check_root
from occdata.nuscenes.rig import RigChoice
from occdata.nuscenes.splits import SplitChoice
from occdata.runtime.cluster import ClusterConfig
from occdata.runtime.storage import is_remote
from occdata.store.reader import store_location
from occdata.store.sample import SampleOptions

__all__ = ["ROOT_GTS", "BuildConfig", "GtsDefault", "LabelsSource", "check_out"]


class GtsDefault(enum.Enum):
    """`BuildConfig.gts` when no folder is named: `<root>/gts` if it exists (Occ3D-nuScenes keeps its
    labels there), else no labels."""

    ROOT = "<root>/gts"


ROOT_GTS = GtsDefault.ROOT


@dataclass(frozen=True)
class LabelsSource:
    """The labels folder a build reads (None: none), whether a folder that no sample finds its file
    in is an error, and the sentence that tells the user which folder it is and why."""

    folder: Path | None
    required: bool
    note: str


@dataclass(frozen=True)
class BuildConfig:
    """`occdata build` options. `out`: a folder or an fsspec URL (s3://bucket/data.zarr). `gts`: the
    labels folder, `ROOT_GTS` (`<root>/gts` when it exists: what the command does without --gts) or
    None (no labels). `labels_required` (a named folder only): a folder in which no sample finds its
    file is an error (a wrong folder would give a silently unlabelled store). `cluster`: where the
    block tasks run. `grid`: the grid of the labels files (`--grid`; None: Occ3D's, or OpenOcc v2's
    when the files have flow), which becomes the store's label grid. `rig`: the cameras and LiDARs
    (`--cameras`, `--lidars`, `--reference-lidar`; default every one of the tables). `scene_splits`: where
    each scene's split comes from (`--split-file`, `--unlisted-split`)."""

    root: Path
    out: Path | str
    version: str | None = None
    gts: Path | GtsDefault | None = None
    labels_required: bool = True
    splits: tuple[str, ...] = ()
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    resume: bool = False
    on_error: Literal["fail", "skip"] = "fail"
    block_samples: int = 32
    options: SampleOptions = field(default_factory=SampleOptions)
    progress: bool = True
    grid: GridSpec | None = None
    rig: RigChoice = field(default_factory=RigChoice)
    scene_splits: SplitChoice = field(default_factory=SplitChoice)

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        if self.gts is not None and not isinstance(self.gts, GtsDefault):
            object.__setattr__(self, "gts", Path(self.gts))
        object.__setattr__(self, "splits", tuple(self.splits))
        if not isinstance(self.cluster, ClusterConfig):
            raise OccDataError(f"cluster must be a ClusterConfig, got {type(self.cluster).__name__}")
        if self.block_samples < 1:
            raise OccDataError(f"--block-samples must be >= 1, got {self.block_samples}")
        if self.on_error not in ("fail", "skip"):
            raise OccDataError(f"--on-error must be fail or skip, got {self.on_error!r}")
        if not 0.05 <= self.options.image_scale <= 1.0:
            raise OccDataError("--image-scale must be in [0.05, 1]")
        if not 1 <= self.options.jpeg_quality <= 100:
            raise OccDataError(f"--jpeg-quality must be in [1, 100], got {self.options.jpeg_quality}")

    def check_paths(self) -> None:
        """One line for a --root that is no folder or a local --out that cannot be a store."""
        check_root(self.root)
        check_out(store_location(self.out))

    def labels(self) -> LabelsSource:
        """Where this build's labels come from (resolves `ROOT_GTS`; `build_store` checks that a named
        folder exists, after the tables). A --root or --out that cannot work is said first (`check_paths`)."""
        self.check_paths()
        if isinstance(self.gts, GtsDefault):
            found = self.root / "gts"
            if found.is_dir():
                return LabelsSource(found, False, f"labels: {found} (found in the dataset root)")
            return LabelsSource(None, False, f"labels: none (no --gts, and {found} does not exist): the store "
                                             "will be unlabelled")
        if self.gts is None:
            return LabelsSource(None, False, "labels: none: the store will be unlabelled")
        return LabelsSource(self.gts, self.labels_required, f"labels: {self.gts} (--gts)")


def check_out(out: str) -> None:
    """One line, before anything is read or written, for a local `out` that cannot be a store: a file,
    or a folder that holds something else. An empty folder is fine: the new store takes its place."""
    if is_remote(out) or not os.path.lexists(out):
        return
    path = Path(out)
    if not path.is_dir():
        raise OccDataError(f"--out {out} is a file, not a store folder: choose another --out (or remove the file)")
    entries = sorted(p.name for p in path.iterdir())
    if entries and "zarr.json" not in entries:
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise OccDataError(f"--out {out} is a folder that holds no zarr store ({len(entries)} entries: {shown}): "
                           "choose another --out, or an empty or new folder")
