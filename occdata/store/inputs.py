"""What a build reads besides the options: the selected samples, their labels files and LiDAR sweeps,
and what each sample's record needs from the whole selection (scene, split, temporal indices)."""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from occdata.constants import GRID
from occdata.errors import OccDataError
from occdata.formats.gridfiles import LabelSite, grid_label_path, read_grid_label
from occdata.formats.gridspec import GridSpec, LabelLayout
from occdata.formats.occ3d import LABEL_FILE, OPENOCC_V2, label_keys, label_relpaths
from occdata.nuscenes import LidarRecord, NuScenesDataset, load_nuscenes
from occdata.nuscenes.columns import TextColumn
from occdata.nuscenes.reader import confined_path, dataset_root
from occdata.nuscenes.records import LazySamples
from occdata.store.blocks import SampleInput
from occdata.store.config import BuildConfig, check_out
from occdata.store.labelgrid import is_default_grid
from occdata.store.reader import store_location
from occdata.store.sample import static_arrays, temporal_indices

__all__ = ["BuildInputs", "Histories", "LabelFiles", "check_sweep_files", "find_grid_label_files", "find_label_files",
           "label_format", "read_inputs", "scene_positions"]


class Histories(Sequence[tuple[LidarRecord, ...]]):
    """Per sample, its previous LiDAR sweeps (`NuScenesDataset.lidar_histories(i, n_sweeps)`), made when
    asked: the records of ten sweeps a sample grew with the dataset."""

    def __init__(self, ds: NuScenesDataset, n_sweeps: int) -> None:
        self.ds, self.n_sweeps = ds, n_sweeps

    def __len__(self) -> int:
        return len(self.ds.samples)

    def __getitem__(self, i: int | slice) -> Any:
        if isinstance(i, slice):
            return [self[k] for k in range(len(self))[i]]
        return self.ds.lidar_histories(range(len(self))[i], self.n_sweeps)

    def __iter__(self) -> Iterator[tuple[LidarRecord, ...]]:
        return (self[i] for i in range(len(self)))


@dataclass(frozen=True, eq=False)
class BuildInputs:
    """The selection a build converts, `n` samples: `labels` and `histories` per sample (its labels
    file or None, its previous LiDAR sweeps, both made when asked); `scene_index`, `split_code`,
    `prev_index` `(n,)` and `prev_valid` `(n, ...)` as `temporal_indices` gives them; `gts` the labels
    folder read; `label_format` its files' format ("occ3d", or "openocc-v2": the store gets
    `labels/flow`); `grid` the files' grid when not Occ3D's (None otherwise)."""

    ds: NuScenesDataset
    gts: Path | None
    labels: LabelFiles
    histories: Histories
    split_names: tuple[str, ...]
    scene_index: np.ndarray
    split_code: np.ndarray
    prev_index: np.ndarray
    prev_valid: np.ndarray
    label_format: str = "occ3d"
    grid: GridSpec | None = None

    @property
    def flow(self) -> bool:
        return self.label_format == OPENOCC_V2

    def sample_input(self, i: int, config: BuildConfig, tok_width: int) -> SampleInput:
        """What converting sample `i` needs (`tok_width`: the store's token length)."""
        s = self.ds.samples[i]
        static = static_arrays(s, int(self.scene_index[i]), int(self.split_code[i]), self.prev_index[i],
                               self.prev_valid[i], tok_width)
        return SampleInput(i, s, static, self.labels[i], config.options, self.histories[i], self.label_format,
                           self.grid)


def read_inputs(config: BuildConfig) -> BuildInputs:
    """The tables, sweeps and labels files of `config`, checked before anything is written (and `--out`
    before the tables are read)."""
    check_out(store_location(config.out))
    n_sweeps = config.options.lidar_sweeps
    ds = load_nuscenes(config.root, config.version, sweeps=n_sweeps > 0, rig=config.rig,
                       splits=config.scene_splits).select(config.splits or None)
    if not ds.samples:
        raise OccDataError(f"no samples selected under {config.root} (splits: {list(config.splits) or 'all'})")
    histories = Histories(ds, n_sweeps)
    check_sweep_files(histories, n_sweeps)
    source = config.labels()
    if source.folder is not None and not source.folder.is_dir():
        raise OccDataError(f"labels folder not found: {source.folder}")
    labels = LabelFiles.none(len(ds.samples))
    grid = None if is_default_grid(config.grid) else config.grid
    if source.folder is not None:
        labels, ds = (find_label_files(source.folder, ds, source.required) if grid is None
                      else find_grid_label_files(source.folder, ds, source.required, grid))
        histories = Histories(ds, n_sweeps)
    _check_first_label(labels, grid)
    split_names = sorted({sc.split for sc in ds.scenes})
    scene_index, index_in_scene = scene_positions(ds)
    split_of = {name: i for i, name in enumerate(split_names)}
    split_code = np.array([split_of[sc.split] for sc in ds.scenes], dtype=np.int64)[scene_index]
    prev_index, prev_valid = temporal_indices(scene_index, index_in_scene)
    return BuildInputs(ds, source.folder, labels, histories, tuple(split_names), scene_index, split_code,
                       prev_index, prev_valid, label_format(labels) if grid is None else "occ3d", grid)


def scene_positions(ds: NuScenesDataset) -> tuple[np.ndarray, np.ndarray]:
    """`(n,) int64` each sample's scene (position in `ds.scenes`) and its index in that scene, from the
    scenes' token lists (no record is made)."""
    scene_index = np.full(len(ds.samples), -1, dtype=np.int64)
    index_in_scene = np.zeros(len(ds.samples), dtype=np.int64)
    for k, sc in enumerate(ds.scenes):
        for j, tok in enumerate(sc.sample_tokens):
            i = ds.index_of(tok)
            scene_index[i], index_in_scene[i] = k, j
    if (scene_index < 0).any():
        raise OccDataError("a sample belongs to no scene of the selection")  # a dataset made in code
    return scene_index, index_in_scene


def _check_first_label(labels: list[Path | None], grid: GridSpec | None) -> None:
    """Refuse, before anything is written, a labels tree whose first file is not on the build's grid
    (one line saying which options name the right grid), rather than failing every sample."""
    first = next((p for p in labels if p is not None), None)
    if first is None:
        return
    want = GRID.shape if grid is None else grid.shape
    hint = ("pass --gts-grid NAME or --voxel-size V [--range ...] as the labels were written (occdata labels/synth "
            "put each grid in gts/<grid>/)")
    name = "occ3d" if grid is None else grid.name
    try:
        if grid is None or grid.layout in (LabelLayout.OCC3D, LabelLayout.OPENOCC_V2):
            with np.load(first, allow_pickle=False) as npz:
                shape = tuple(npz["semantics"].shape) if "semantics" in npz.files else want
        else:  # sparse rows: indices beyond the grid say it is another one
            shape = read_grid_label(grid, first)["semantics"].shape
    except OccDataError as exc:
        if "outside" in str(exc):
            raise OccDataError(f"{exc}: not the build's grid {name} {want}; {hint}") from None
        return
    except (OSError, ValueError, EOFError, KeyError):
        return  # a damaged file fails its own sample, naming it
    if shape != want:
        raise OccDataError(f"labels file {first} is of shape {shape}, not the build's grid {name} {want}; {hint}")


def label_format(labels: list[Path | None]) -> str:
    """The format of a labels tree, from its first readable file: "openocc-v2" if that file has a
    `flow` array (OpenOcc v2's files, ours from `occdata labels --grid openocc-v2`: its class ids, and
    the store gets `labels/flow`), else "occ3d". Only that file's zip directory is read; a file of
    the other format later fails its sample with one line (a tree must hold one format)."""
    for path in labels:
        keys = label_keys(path) if path is not None else None
        if keys is not None:
            return OPENOCC_V2 if "flow" in keys else "occ3d"
    return "occ3d"


def check_sweep_files(histories: Iterable[tuple[LidarRecord, ...]], n_sweeps: int) -> None:
    """Raise one `OccDataError` line if any sweep file that `--lidar-sweeps` needs is not a file:
    it names the first missing one and how many of the needed files were found. `histories` come in
    sample order: a sweep shared by several samples' histories is shared by consecutive ones, so
    each is checked once against the previous history alone (memory does not grow with the samples)."""
    n_needed, missing, first = 0, 0, None
    previous: set[str] = set()
    for h in histories:
        current = {sw.token for sw in h}
        for sw in h:
            if sw.token in previous:
                continue
            previous.add(sw.token)  # a history may name a sweep twice (two LiDARs share none, but be safe)
            n_needed += 1
            if not sw.path.is_file():
                missing += 1
                first = first or sw
        previous = current
    if first is not None:
        raise OccDataError(
            f"--lidar-sweeps {n_sweeps}: missing sweep file {first.path} (sample_data {first.token!r}); "
            f"{n_needed - missing} of the {n_needed} sweep files needed were found. A keyframe-only "
            "download has no sweeps/ folder: add the sweeps, or use --lidar-sweeps 0"
        )


class LabelFiles(Sequence[Path | None]):
    """Per sample, its labels file or None: paths under `gts` kept as text in one buffer (a `Path`
    object per sample grew with the dataset)."""

    def __init__(self, gts: Path | None) -> None:
        self.gts, self._rel = gts, TextColumn()

    def append(self, path: Path | None) -> None:
        self._rel.append("" if path is None else str(path.relative_to(self.gts)))

    def __len__(self) -> int:
        return len(self._rel)

    def __getitem__(self, i: int | slice) -> Any:
        if isinstance(i, slice):
            return [self[k] for k in range(len(self))[i]]
        rel = self._rel.get(range(len(self))[i])
        return self.gts / rel if rel and self.gts is not None else None

    @classmethod
    def none(cls, n: int) -> LabelFiles:
        out = cls(None)
        for _ in range(n):
            out.append(None)
        return out


def find_label_files(
    gts: Path, ds: NuScenesDataset, required: bool
) -> tuple[LabelFiles, NuScenesDataset]:
    """Per sample, its `labels.npz` under `gts` (nested `<scene>/<token>/` first, then flat
    `<token>/`), or None. Scene names and tokens come from the tables: a label path that would leave
    `gts` marks that sample with a problem (the sample fails, naming the row). With `required`, no
    match for any sample is an error that shows the expected layout and one expected path.
    """
    found = LabelFiles(dataset_root(gts))
    problems: dict[int, str] = {}
    for i, (scene_name, token) in enumerate(_sites(ds)):
        where = f"scene {scene_name!r} / sample {token!r} (labels path under --gts)"
        path: Path | None = None
        try:
            candidates = [confined_path(gts, rel, where) for rel in label_relpaths(scene_name, token)]
            path = next((c for c in candidates if os.path.lexists(c)), None)
        except OccDataError as exc:
            problems[i] = str(exc)
        found.append(path)
    if required and ds.samples and not any(found):
        s = ds.samples[0]
        nested, flat = label_relpaths(s.scene_name, s.token)
        raise OccDataError(
            f"no label file under {gts} matches any of the {len(ds.samples)} samples; expected "
            f"{gts}/<scene name>/<sample token>/{LABEL_FILE} or {gts}/<sample token>/{LABEL_FILE}, "
            f"e.g. {gts / nested} (check --gts; leave it out for samples without labels, e.g. the test split; "
            "labels of another grid need --gts-grid NAME or --voxel-size)"
        )
    return found, ds.with_problems(problems)


def _sites(ds: NuScenesDataset) -> Iterator[tuple[str, str]]:
    """(scene name, sample token) of each sample in order, without making the records of a dataset that
    packs them (`LazySamples`: one pass over every record cost ~70 us a sample)."""
    if isinstance(ds.samples, LazySamples):
        scene_index, _ = scene_positions(ds)
        return ((ds.scenes[k].name, t) for k, t in zip(scene_index.tolist(), ds.sample_tokens(), strict=True))
    return ((s.scene_name, s.token) for s in ds.samples)


def find_grid_label_files(gts: Path, ds: NuScenesDataset, required: bool,
                          spec: GridSpec) -> tuple[LabelFiles, NuScenesDataset]:
    """Per sample, its label file of `spec` under `gts` in the grid's own layout
    (`occdata.formats.gridfiles.grid_label_path`), or None; `required` as in `find_label_files`."""
    found = LabelFiles(dataset_root(gts))
    problems: dict[int, str] = {}
    for i, s in enumerate(ds.samples):
        site = LabelSite(s.scene_name, s.scene_token, s.token, s.lidar.token, s.lidar.path.name)
        path: Path | None = None
        try:  # names from the tables are data: the path must stay under gts
            rel = str(grid_label_path(spec, Path("."), site))
            path = confined_path(gts, rel, f"scene {s.scene_name!r} / sample {s.token!r} (labels path under --gts)")
        except OccDataError as exc:
            problems[i] = str(exc)
        found.append(path if path is not None and os.path.lexists(path) else None)
    ds = ds.with_problems(problems)
    if required and ds.samples and not any(found):
        s = ds.samples[0]
        expect = grid_label_path(spec, gts, LabelSite(s.scene_name, s.scene_token, s.token, s.lidar.token,
                                                      s.lidar.path.name))
        raise OccDataError(f"no {spec.name} label file under {gts} matches any of the {len(ds.samples)} samples; "
                           f"expected e.g. {expect} (check --gts and --grid)")
    return found, ds
