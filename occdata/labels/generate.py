"""`occdata labels`: occupancy labels for every scene of a nuScenes-format tree, on one or more grids.

Output per grid (`occdata.formats.gridspec`; one aggregation per scene serves them all): the Occ3D grid in
`<out>/<scene>/<sample_token>/labels.npz` (`semantics`, `mask_lidar`, `mask_camera`, uint8
(200, 200, 16), 17 = free), exactly Occ3D's layout, so `occdata build --gts <out>` and every peer
codebase read it; every other grid in `<out>/<grid name>/` in its benchmark's own layout
(`occdata.formats.gridfiles`). A scene is one task: its files are written atomically, then its record
`<out>/.scenes/<scene>.json` (the scene is finished only once that exists), and at the end the
manifest `<out>/labels.json` is assembled from the records (idempotent). `--resume` skips scenes
with a record. The same input gives byte-identical files.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from occdata.constants import CLASS_NAMES, FREE_LABEL
from occdata.errors import OccDataError
from occdata.fileio import remove_stale_temps, write_atomic
from occdata.formats.gridfiles import LAYOUT_FILES, LabelSite, write_grid_label
from occdata.formats.gridspec import GRID_PRESETS, GridSpec, LabelLayout
from occdata.labels.flat import FLAT_CLEARANCE
from occdata.labels.options import LabelOptions, LabelSources, SceneCounts
from occdata.labels.scene import label_scene
from occdata.nuscenes import NuScenesDataset, SampleRecord, find_version, load_nuscenes, validate_sample
from occdata.nuscenes.annotations import load_annotations
from occdata.nuscenes.lidarseg import lidarseg_index_names, load_lidarseg_index, occ3d_lut
from occdata.nuscenes.rig import Rig, RigChoice
from occdata.nuscenes.splits import SplitChoice
from occdata.runtime.cluster import ClusterConfig, LazyTasks, cluster_client, run_tasks
from occdata.runtime.lock import store_lock
from occdata.runtime.tasks import StopCheck, no_stop

__all__ = ["ALGORITHM_VERSION", "LabelsConfig", "LabelsReport", "SceneJob", "generate_labels", "load_inputs",
           "run_scene", "scene_modes", "scene_record_path"]

# Bumped whenever the labels a given input produces change (2: carving's counts exact, slots by sweep).
ALGORITHM_VERSION = 2
_RECORDS = ".scenes"


@dataclass(frozen=True)
class LabelsConfig:
    """`occdata labels` options. `scenes`: scene names to label (None: all of the chosen splits);
    `cluster`: where the scene tasks run (as `occdata.store.build.BuildConfig.cluster`); `rig`: the
    cameras (camera masks) and LiDARs (aggregation, LiDAR masks) used (`--cameras`, `--lidars`,
    `--reference-lidar`; default every one of the tables); `scene_splits`: where each scene's split comes
    from (`--split-file`, `--unlisted-split`), which `splits` then selects."""

    root: Path
    out: Path
    version: str | None = None
    options: LabelOptions = LabelOptions()
    scenes: tuple[str, ...] | None = None
    splits: tuple[str, ...] | None = None
    resume: bool = False
    progress: bool = True
    cluster: ClusterConfig = ClusterConfig()
    grids: tuple[GridSpec, ...] = (GRID_PRESETS["occ3d"],)
    rig: RigChoice = field(default_factory=RigChoice)
    scene_splits: SplitChoice = field(default_factory=SplitChoice)

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        object.__setattr__(self, "out", Path(self.out))
        names = [g.name for g in self.grids]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"grids must be one or more distinct grids, got {names}")

    def grid_root(self, spec: GridSpec) -> Path:
        """Where `spec`'s files go: `out` itself for Occ3D's grid (what `occdata build --gts` reads),
        `out/<grid name>` for the others."""
        return self.out if spec.name == "occ3d" else self.out / spec.name


@dataclass(frozen=True)
class LabelsReport:
    scenes_done: int
    scenes_skipped: int  # finished earlier (--resume)
    keyframes: int
    with_lidarseg: bool
    manifest: Path
    modes: dict[str, str] = field(default_factory=dict)  # scene -> boxes / naive / carve / boxes+carve


def scene_record_path(out: Path, scene: str) -> Path:
    return Path(out) / _RECORDS / f"{scene}.json"


def load_inputs(cfg: LabelsConfig) -> tuple[LabelSources, str]:
    """The tables (with sweeps when used), boxes and lidarseg of `cfg.root`; and the version read."""
    version = find_version(cfg.root, cfg.version)
    ds = load_nuscenes(cfg.root, version, sweeps=cfg.options.all_sweeps, rig=cfg.rig,
                       splits=cfg.scene_splits).select(cfg.splits)
    if cfg.scenes is not None:
        missing = sorted(set(cfg.scenes) - {sc.name for sc in ds.scenes})
        if missing:
            raise OccDataError(f"scene(s) not in {cfg.root}/{version}: {', '.join(missing)}")
        ds = _only_scenes(ds, set(cfg.scenes))
    for s in ds.samples:
        validate_sample(s)
    seg = load_lidarseg_index(cfg.root, version)
    lut = occ3d_lut(lidarseg_index_names(cfg.root, version)) if seg else None
    return LabelSources(ds, load_annotations(cfg.root, version), seg, lut), version


def _only_scenes(ds: NuScenesDataset, names: set[str]) -> NuScenesDataset:
    return ds.only_scenes(tuple(sc for sc in ds.scenes if sc.name in names))


# Options that exist for carving alone: recorded only when some scene is carved, so that the box path's
# manifest keeps its bytes.
_CARVE_KEYS = ("carve", "dynamic_class", "carve_options")
_CARVE_COUNTS = ("mode", "dynamic_points", "carve_voxels")


def scene_modes(inputs: LabelSources, options: LabelOptions) -> dict[str, str]:
    """Scene name -> how it is labelled (`LabelOptions.mode`: boxes, naive, carve, boxes+carve): a tree
    may have boxes for some scenes and not for others."""
    boxed = set(inputs.annotations.boxes_by_sample)
    return {sc.name: options.mode(any(t in boxed for t in sc.sample_tokens), len(sc.sample_tokens))
            for sc in inputs.dataset.scenes}


def _options_dict(cfg: LabelsConfig, version: str, with_seg: bool,
                  modes: dict[str, str] | None = None, rig: Rig | None = None) -> dict[str, Any]:
    masks = cfg.options.image_masks
    opts = dataclasses.asdict(dataclasses.replace(cfg.options, image_masks=None))
    del opts["image_masks"]  # recorded only when given, in words: a run without masks keeps its bytes
    if masks is not None:
        opts["image_masks"] = masks.describe()
    if with_seg:  # lidarseg gives the ground its class: a lidarseg tree's manifest keeps its bytes
        del opts["ground_class"]
    carved = sorted(name for name, mode in (modes or {}).items() if "carve" in mode)
    if not carved:
        opts = {k: v for k, v in opts.items() if k not in _CARVE_KEYS}
    if not opts["deskew"]:  # recorded when on only: the manifests from before it keep their bytes
        del opts["deskew"]
    static = _static_words(cfg.options)
    header = {
        "generator": "occdata labels",
        "algorithm_version": ALGORITHM_VERSION,
        "package_version": _package_version(),
        "source": {"root": str(cfg.root), "version": version},
        "options": opts,
        "lidarseg": with_seg,
        "classes": ("keyframe points: lidarseg mapped to Occ3D (noise, ego dropped); sweep points: nearest "
                    "labelled keyframe point" if with_seg else
                    f"points in a box: the box's category; {static}"),
        "layout": "<scene>/<sample_token>/labels.npz: semantics, mask_lidar, mask_camera; uint8 "
                  f"{GRID_PRESETS['occ3d'].shape}; {FREE_LABEL} = free",
        "grids": [{**spec.describe(), "folder": str(cfg.grid_root(spec).relative_to(cfg.out)),
                   "files": LAYOUT_FILES[spec.layout]} for spec in cfg.grids],
    }
    if carved:
        header["carving"] = _carving_words(cfg.options, with_seg, carved)
    # Recorded only where they are not nuScenes' defaults, so that a nuScenes manifest keeps its bytes.
    if rig is not None and not rig.is_nuscenes:
        header["rig"] = rig.as_attr()
    if cfg.scene_splits != SplitChoice():
        header["scene_splits"] = cfg.scene_splits.describe()
    return header


def _static_words(o: LabelOptions) -> str:
    """What the classes of points outside boxes mean without lidarseg, in words (labels.json)."""
    others = (f"{o.static_class} ({CLASS_NAMES[o.static_class]}): every point outside a box; the tree has no "
              "lidarseg, so this class says 'occupied, not an annotated object', not what it is")
    words = f"static points: class {others}"
    if o.splits_ground:
        words += (f"; a point within {FLAT_CLEARANCE} m over the scene's ground (the lowest surface any keyframe saw "
                  f"in its 0.5 m column, heights aligned): class {o.ground_class} ({CLASS_NAMES[o.ground_class]}), "
                  "a stand-in meaning 'flat ground' (road, sidewalk and terrain alike: geometry cannot tell them "
                  "apart); a flat voxel under a voxel of something else takes its other points' class, or the "
                  "class above")
    if o.image_masks is not None:
        words += ("; where the user's image masks give a class (--image-masks: each point projected into the camera "
                  "nearest in time, where it is the visible surface), a voxel takes the majority of its points' "
                  "mask classes, the classes above only where no point of it has one")
    return words


def _carving_words(o: LabelOptions, with_seg: bool, carved: list[str]) -> dict[str, Any]:
    """What carving did and what its classes mean, in words (labels.json)."""
    c = o.carve_options
    dyn = ("lidarseg classes as for every point (ground, buildings and vegetation are never dynamic)"
           if with_seg else f"{o.dynamic_class} ({CLASS_NAMES[o.dynamic_class]}): a stand-in meaning 'on something "
           "that moved' (a car, a cyclist, a pedestrian alike); the tree has no lidarseg to say which")
    return {
        "scenes": carved,
        "rule": ("a time slot is one sweep of the rig (a keyframe's LiDARs together, the n-th sweep before it of each "
                 f"LiDAR together); a point outside every box is dynamic when at least {c.min_frames} other time "
                 "slots' LiDAR rays "
                 f"crossed its {c.voxel_size} m voxel (global frame), and at least {c.ratio:g} times as many slots "
                 f"as had a return there ({c.ratio_seg:g} times for points with a lidarseg class); a ray's last "
                 f"clamp({c.graze_height} m / |sin elevation|, {c.margin}, {c.graze_max}) m before its return and "
                 f"the voxels within {c.near} voxel(s) of a return of the same slot"
                 + (f" (above a return within {c.ground_clearance} m of the scene's ground: {c.near_above_ground} "
                    "voxel(s) up)" if c.near_above_ground < c.near and c.ground_clearance > 0 else "")
                 + " are no evidence"
                 + (f"; a point is also dynamic when at least {c.min_gone} slots saw its voxel empty after the "
                    "voxel's last return or before its first (it left, or it came)" if c.min_gone > 0 else "")
                 + ("; each slot's heights are first corrected by its height error, fitted to the ground the "
                    "keyframes share" if c.align_heights else "")
                 + (f"; a point within {c.ground_clearance} m of the scene's ground (the lowest surface any keyframe "
                    "saw in its 0.5 m column) is never dynamic" if c.ground_clearance > 0 else "")),
        "static": "the other points: aggregated over the scene in the global frame and drawn at every keyframe",
        "dynamic": (f"drawn only at the keyframes within {c.window} s of their frame, where they were then; "
                    f"class {dyn}"),
    }


def _package_version() -> str:
    try:
        return metadata.version("fastocc")
    except metadata.PackageNotFoundError:
        return "unknown"


def _site(sample: SampleRecord) -> LabelSite:
    return LabelSite(sample.scene_name, sample.scene_token, sample.token, sample.lidar.token, sample.lidar.path.name)


def _commit(out: Path, header: dict[str, Any], scenes: Iterable[str]) -> Path:
    """Assemble `labels.json` from the scene records (idempotent)."""
    records = {}
    for name in sorted(scenes):
        path = scene_record_path(out, name)
        if path.is_file():
            records[name] = json.loads(path.read_text())
    manifest = {**header, "scenes": records,
                "totals": {k: sum(r["counts"][k] for r in records.values()) for k in ("keyframes", "points")}}
    write_atomic(out / "labels.json", json.dumps(manifest, indent=1, sort_keys=True).encode())
    return out / "labels.json"


def _check_out(cfg: LabelsConfig, header: dict[str, Any]) -> None:
    """A fresh run needs an output without our records; a resumed one needs the same settings."""
    records = sorted((cfg.out / _RECORDS).glob("*.json")) if (cfg.out / _RECORDS).is_dir() else []
    if records and not cfg.resume:
        raise OccDataError(f"{cfg.out} already holds labels of {len(records)} scene(s); pass --resume to "
                           "continue, or choose another --out")
    for path in records:
        old = json.loads(path.read_text()).get("settings")
        if old != _settings(header):
            raise OccDataError(f"{path} was written with other settings ({old}); use another --out")


def _settings(header: dict[str, Any]) -> dict[str, Any]:
    """What a resumed run must share with the records it continues (the rig and split rule only where
    the header has them: a nuScenes record keeps its bytes)."""
    out = {"algorithm_version": header["algorithm_version"], "options": header["options"],
           "lidarseg": header["lidarseg"], "grids": [g["name"] for g in header["grids"]]}
    return out | {k: header[k] for k in ("rig", "scene_splits") if k in header}


def _counts_record(counts: SceneCounts) -> dict[str, Any]:
    """A scene's counts for its record; the carving ones only where it was carved."""
    out = dataclasses.asdict(counts)
    if "carve" not in counts.mode:
        out = {k: v for k, v in out.items() if k not in _CARVE_COUNTS}
    return out


@dataclass(frozen=True)
class SceneJob:
    """One task: label scene `scene` of `cfg`'s tree. `inputs` is that scene's slice of what the
    client read (`LabelSources.for_scene`: its records, boxes and lidarseg paths, never the tables):
    a worker holds only its task's rows and never opens a table file, so its memory does not grow
    with the number of scenes in the tree."""

    cfg: LabelsConfig
    scene: str
    settings: str  # JSON of `_settings(header)`, copied into the scene's record
    keyframes: int
    inputs: LabelSources = field(compare=False, repr=False)

    def __post_init__(self) -> None:
        names = [sc.name for sc in self.inputs.dataset.scenes]
        if names != [self.scene]:
            raise ValueError(f"a SceneJob carries the slice of scene {self.scene!r} alone, not of {names[:3]}")

    @property
    def units(self) -> int:
        return self.keyframes

    def run(self, should_stop: StopCheck = no_stop) -> dict[str, int]:
        """Label the scene and write its files, then its record (idempotent: a rerun rewrites the same
        bytes). Returns the scene's counts."""
        scene = self.inputs.dataset.scenes[0]
        flow = [g.name for g in self.cfg.grids if g.layout is LabelLayout.OPENOCC_V2]  # the layout that holds flow
        labels, counts = label_scene(self.inputs, scene, self.cfg.options, should_stop, self.cfg.grids, flow)
        record = {"settings": json.loads(self.settings), "counts": _counts_record(counts),
                  "samples": sorted(labels[self.cfg.grids[0].name])}
        sites = {s.token: _site(s) for s in self.inputs.dataset.samples}  # the scene's slice: its samples
        for spec in self.cfg.grids:
            for token, arrays in labels[spec.name].items():
                write_grid_label(spec, self.cfg.grid_root(spec), sites[token], arrays)
        write_atomic(scene_record_path(self.cfg.out, scene.name),
                     json.dumps(record, indent=1, sort_keys=True).encode())
        return record["counts"]


def run_scene(job: SceneJob) -> dict[str, int]:
    """`job.run()` without a stop check."""
    return job.run(no_stop)


def generate_labels(cfg: LabelsConfig, client: Any = None) -> LabelsReport:
    """Label every chosen scene (see the module docstring): one `SceneJob` task per scene, on
    `cfg.cluster` (occdata.runtime.cluster: here, a LocalCluster of N workers, or an existing scheduler), or
    on `client`, a `distributed.Client` already open. Raises `occdata.runtime.cluster.Interrupted` on Ctrl-C /
    SIGTERM (finished scenes are kept)."""
    inputs, version = load_inputs(cfg)
    modes = scene_modes(inputs, cfg.options)
    header = _options_dict(cfg, version, bool(inputs.lidarseg), modes, inputs.dataset.rig)
    cfg.out.mkdir(parents=True, exist_ok=True)
    with store_lock(cfg.out, "labels"):
        _check_out(cfg, header)
        # What a killed run left half-written (we hold the lock: no other writer is live).
        remove_stale_temps(cfg.out, recursive=True)
        todo = [sc for sc in inputs.dataset.scenes if not scene_record_path(cfg.out, sc.name).is_file()]
        skipped = len(inputs.dataset.scenes) - len(todo)
        settings = json.dumps(_settings(header), sort_keys=True)
        # The tables are read once, here; each task carries its scene's slice (O(scene) to make).
        # Each task made when it is sent: only the scenes in flight have their slice at once.
        jobs = LazyTasks(todo, lambda sc: SceneJob(cfg, sc.name, settings, len(sc.sample_tokens), inputs.for_scene(sc)))
        with contextlib.nullcontext(client) if client is not None else cluster_client(cfg.cluster) as run_on:
            run_tasks(run_on, jobs, desc="labels", unit="sample", progress=cfg.progress,
                      total=sum(len(sc.sample_tokens) for sc in todo))
        manifest = _commit(cfg.out, header, (sc.name for sc in inputs.dataset.scenes))
    return LabelsReport(len(todo), skipped, len(inputs.dataset.samples), bool(inputs.lidarseg), manifest, modes)
