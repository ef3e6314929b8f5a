"""Load a nuScenes-format version folder into frozen keyframe records (docs/design.md#frames-and-names).

Only what occupancy needs is kept: keyframe samples with the rig's cameras and LiDARs (`rig.py`: read
from the tables, never assumed), each sensor with its calibration and its own ego pose; on request
(`sweeps=True`) also each LiDAR's non-keyframe sweeps before each keyframe (`SampleRecord.sweeps`,
`extra_sweeps`, through the `prev` links). Every foreign key is resolved here, so a broken tree fails
early with one line naming the table and token.
"""

from __future__ import annotations

import bisect
import os
import re
from array import array
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from dataclasses import field as dc_field
from pathlib import Path
from typing import Any

import numpy as np

from occdata.errors import OccDataError
from occdata.nuscenes.columns import ColumnTable
from occdata.nuscenes.packed import PackedSamples
from occdata.nuscenes.pointfiles import is_pcd, read_pcd
from occdata.nuscenes.records import (
    CameraRecord,
    LazySamples,
    LidarRecord,
    NuScenesDataset,
    SampleRecord,
    SceneRecord,
)
from occdata.nuscenes.rig import Rig, RigChoice, resolve_rig, sensor_modalities
from occdata.nuscenes.rows import RowProblem, field, floats, integer, link, pose, ref, short, timestamp_us
from occdata.nuscenes.splits import AUTO_SPLIT, SplitChoice, auto_split, official_split
from occdata.nuscenes.tables import TokenSet, load_table, usable_as_file_name

__all__ = [
    "SPLIT_TAG",
    "TableIndex",
    "check_root",
    "confined_path",
    "dataset_root",
    "find_version",
    "load_lidar_points",
    "load_nuscenes",
    "read_tables",
    "validate_sample",
]

# Non-official scenes (synthetic or custom data) may carry "split=<name>" in their description.
SPLIT_TAG = re.compile(r"\bsplit=([A-Za-z0-9_]+)")
# log.json is optional: MAN TruckScenes ships none (its scenes' log_token is ""); the log gives only the location.
_NEEDED_TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor")


def check_root(root: Path | str) -> Path:
    """`root` as a Path when it is a folder; else one `OccDataError` line: not found, or a file."""
    root = Path(root)
    if root.is_dir():
        return root
    if root.exists():
        raise OccDataError(f"dataset root {root} is a file, not a folder: --root names the folder that holds the "
                           "version folder (v1.0-trainval/, ...), samples/ and sweeps/")
    raise OccDataError(f"dataset root not found: {root}")


def find_version(root: Path, version: str | None) -> str:
    """The version folder to read: `version` if given, else the only `v*` folder holding scene.json."""
    root = check_root(root)
    found = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "scene.json").is_file())
    if version is not None:
        if not (root / version).is_dir():
            raise OccDataError(
                f"version folder not found: {root / version} (present: {', '.join(found) or 'none'})"
            )
        return version
    if not found and (root / "scene.json").is_file():
        raise OccDataError(f"--root {root} is a version folder itself (it holds scene.json): give its parent, "
                           f"{root.parent}")
    if not found:
        raise OccDataError(f"{root} holds no nuScenes tables: no folder in it has a scene.json (expected e.g. "
                           f"{root / 'v1.0-trainval' / 'scene.json'})")
    if len(found) != 1:
        raise OccDataError(f"cannot choose a version folder under {root}: found {found}; pass --version")
    return found[0]


def dataset_root(root: Path | str) -> Path:
    """The absolute form of a dataset root, with its symlinks kept (docs/design.md#frames-and-names: record paths).

    Record paths are `dataset_root(root) / filename`: a root that is a symlink (or lies under one,
    as on clusters) stays as the user named it, so paths compare equal to `root / filename`. Only
    a root with a `..` component is resolved, since `..` after a symlink means the link target's
    parent, which no lexical rule gets right.
    """
    path = Path(root).absolute()
    if ".." in path.parts:
        return path.resolve()
    return Path(os.path.normpath(path))


def confined_path(root: Path, relative: Any, where: str) -> Path:
    """`dataset_root(root) / relative`, refused unless it stays inside the root (docs/design.md: paths from
    tables are data).

    The check is lexical (`..` and absolute paths are refused); symlinks are neither resolved nor
    refused: a symlinked root and symlinks that the user placed in the tree are followed as usual.
    Raises `OccDataError` naming `where` (the row).
    """
    if not isinstance(relative, str) or not relative or "\0" in relative:
        raise OccDataError(f"{where}: path {short(relative)} is not a non-empty string")
    root_text = str(root)
    if not (os.path.isabs(root_text) and os.path.normpath(root_text) == root_text):  # not already a dataset_root
        root_text = str(dataset_root(root))
    # on strings: pathlib's parsing was half of reading a keyframe's records
    joined = os.path.normpath(os.path.join(root_text, relative))
    if os.path.isabs(relative) or not joined.startswith(root_text.rstrip("/") + "/") or joined == root_text:
        raise OccDataError(f"{where}: path {relative!r} points outside {root_text}")
    return Path(joined)


@dataclass(frozen=True, eq=False)
class Keyframes:
    """Per row of sample.json (file order) and channel, the position of its keyframe row in
    sample_data (-1: none): `positions (n_sample_rows, len(channels)) int32`."""

    channels: tuple[str, ...]
    positions: np.ndarray

    def present(self) -> set[str]:
        """The channels with a keyframe row in some sample."""
        return {c for c, col in zip(self.channels, self.positions.T, strict=True) if (col >= 0).any()}


@dataclass(frozen=True, eq=False)
class TableIndex:
    """The rows that `load_nuscenes` needs, keyed by token, and the maps derived from them.

    `sample_data` holds the keyframe rows of the tables' cameras and LiDARs, plus (with `sweeps`) the
    LiDARs' non-keyframe rows; `ego_poses` only the poses of the rig's rows. `samples`, `sample_data`
    and `ego_poses` are `ColumnTable`s (they grow with the dataset). Derived: `rig`,
    `channel_of_calib` (calibrated_sensor token -> sensor channel), `keyframes` (`Keyframes`; read
    through `keyframe_rows`), `n_lidar_rows` (the rig's LiDAR rows: a bound for chain walks).
    """

    root: Path
    version: str
    sweeps: bool
    sensors: dict[str, dict[str, Any]]
    calibs: dict[str, dict[str, Any]]
    logs: dict[str, dict[str, Any]] | None  # None: the tree has no log.json
    scenes: dict[str, dict[str, Any]]
    samples: ColumnTable
    sample_data: ColumnTable
    ego_poses: ColumnTable
    channel_of_calib: dict[str, str]
    keyframes: Keyframes
    n_lidar_rows: int
    notes: tuple[str, ...]  # one line each: identical duplicate rows ignored
    rig: Rig
    # (calibrated_sensor token, is a camera) -> (T_sensor, K): made once, shared (`_calibration`)
    calib_cache: dict[tuple[str, bool], tuple[np.ndarray, np.ndarray | None]] = dc_field(
        default_factory=dict)

    def release(self) -> None:
        """Map out the pages of the big tables' columns read so far (`ColumnTable.release`)."""
        for table in (self.samples, self.sample_data, self.ego_poses):
            table.release()

    def keyframe_positions(self, sample_token: str) -> dict[str, int]:
        """The rig's channels -> the position in sample_data of that sample's keyframe row (in file
        order; absent ones left out)."""
        s_pos = self.samples.position(sample_token)
        if s_pos < 0:
            return {}
        used = set(self.rig.channels)
        found = sorted((p, c) for c, p in zip(self.keyframes.channels, self.keyframes.positions[s_pos].tolist(),
                                              strict=True) if p >= 0 and c in used)
        return {c: p for p, c in found}

    def keyframe_rows(self, sample_token: str) -> dict[str, dict[str, Any]]:
        """`keyframe_positions` with each position's row."""
        return {c: self.sample_data.row_at(p) for c, p in self.keyframe_positions(sample_token).items()}

    def lidar_row(self, token: Any) -> dict[str, Any] | None:
        """The sample_data row `token` if it is a row of one of the rig's LiDARs, else None."""
        pos = self.sample_data.position(token)
        if pos < 0:
            return None
        row = self.sample_data.row_at(pos)
        return row if self.channel_of_calib[row["calibrated_sensor_token"]] in self.rig.lidars else None


def read_tables(root: Path, version: str, sweeps: bool, rig: RigChoice | None = None) -> TableIndex:
    """Load the tables of `<root>/<version>` that the reader needs into a `TableIndex`, with the rig
    (`resolve_rig`) narrowed by `rig`.

    Raises `OccDataError` for a missing table, a dangling calibrated_sensor / sensor / sample token,
    a channel named by two sensors, or two keyframe rows of one channel in one sample.
    """
    vdir = root / version
    for name in _NEEDED_TABLES:
        if not (vdir / f"{name}.json").is_file():
            raise OccDataError(f"missing table: {vdir / f'{name}.json'}")
    notes: list[str] = []
    sensors = load_table(vdir / "sensor.json", warn=notes.append)
    calibs = load_table(vdir / "calibrated_sensor.json", warn=notes.append)
    logs = load_table(vdir / "log.json", warn=notes.append) if (vdir / "log.json").is_file() else None
    scenes = load_table(vdir / "scene.json", warn=notes.append)
    if not scenes:
        raise OccDataError(f"{vdir / 'scene.json'} holds no scenes: nothing to read")
    samples = load_table(vdir / "sample.json", warn=notes.append, columns=True)
    for pos in samples.positions():  # every sample belongs to a scene of the tables
        ref(scenes, field(samples.row_at(pos), "scene_token", "sample"), "scene",
            f"sample {samples.value_at(pos, 'token')!r}")
    channel_of_calib = _channels_of_calibs(calibs, sensors)
    modalities = sensor_modalities(sensors)
    choice = rig or RigChoice()
    wanted = {c for c, m in modalities.items() if m in ("camera", "lidar")}
    keep = _sample_data_filter(calibs, channel_of_calib, modalities, wanted, sweeps)
    all_sample_data = TokenSet()
    sample_data = load_table(vdir / "sample_data.json", keep=keep, warn=notes.append, tokens=all_sample_data,
                             columns=True)
    _check_links(sample_data, all_sample_data)
    keyframes = _keyframes_by_sample(sample_data, samples, channel_of_calib)
    resolved = resolve_rig(modalities, keyframes.present(), choice)
    pose_hashes, n_lidar_rows = _pose_hashes(sample_data, channel_of_calib, resolved)
    sample_data.release()  # the passes above read every row: map their pages out (ColumnTable.release)
    samples.release()
    ego_poses = load_table(vdir / "ego_pose.json", keep=lambda r: _has_hash(pose_hashes, r.get("token")),
                           warn=notes.append, columns=True)
    return TableIndex(
        root=root, version=version, sweeps=sweeps, sensors=sensors, calibs=calibs, logs=logs, scenes=scenes,
        samples=samples, sample_data=sample_data, ego_poses=ego_poses, channel_of_calib=channel_of_calib,
        keyframes=keyframes, n_lidar_rows=n_lidar_rows, notes=tuple(notes), rig=resolved,
    )


_MISSING = object()  # `get_at`'s default for a field a row does not have


def _pose_hashes(sample_data: ColumnTable, channel_of_calib: dict[str, str], rig: Rig) -> tuple[array, int]:
    """The sorted hashes of the ego_pose tokens that the rig's rows name (each must be a string), and
    how many of those rows are the rig's LiDARs'."""
    used, lidars = set(rig.channels), set(rig.lidars)
    hashes = array("q")
    n_lidar = 0
    for pos in sample_data.positions():
        channel = channel_of_calib[sample_data.value_at(pos, "calibrated_sensor_token")]
        if channel not in used:
            continue
        n_lidar += channel in lidars
        pose_tok = sample_data.get_at(pos, "ego_pose_token", _MISSING)
        if pose_tok is _MISSING:
            field(sample_data.row_at(pos), "ego_pose_token", "sample_data")  # raises, naming the row
        if not isinstance(pose_tok, str):
            raise OccDataError(f"sample_data.json: row {sample_data.value_at(pos, 'token')!r} ego_pose_token is "
                               f"not a token ({short(pose_tok)})")
        hashes.append(hash(pose_tok))
    return array("q", sorted(set(hashes))), n_lidar


def _has_hash(sorted_hashes: array, token: Any) -> bool:
    """Whether `hash(token)` is in `sorted_hashes` (a 64-bit collision keeps a row that is not needed)."""
    if not isinstance(token, str):
        return False
    h = hash(token)
    i = bisect.bisect_left(sorted_hashes, h)
    return i < len(sorted_hashes) and sorted_hashes[i] == h


def _channels_of_calibs(calibs: dict[str, dict[str, Any]], sensors: dict[str, dict[str, Any]]) -> dict[str, str]:
    """calibrated_sensor token -> its sensor's channel."""
    out: dict[str, str] = {}
    for tok, cs in calibs.items():
        sensor = ref(sensors, field(cs, "sensor_token", "calibrated_sensor"), "sensor", f"calibrated_sensor {tok!r}")
        out[tok] = field(sensor, "channel", "sensor")
    return out


def _sample_data_filter(
    calibs: dict[str, dict[str, Any]], channel_of_calib: dict[str, str], modalities: dict[str, str],
    wanted: set[str], sweeps: bool,
) -> Callable[[dict[str, Any]], bool]:
    """The sample_data rows to keep: keyframes of the `wanted` channels (cameras and LiDARs); with
    `sweeps` also the LiDARs' non-keyframe rows. A row naming an unknown calibrated_sensor, or whose
    is_key_frame is not a boolean, is an `OccDataError`, whether it is kept or not."""

    def keep(row: dict[str, Any]) -> bool:
        # checked for every row, kept or not: every command refuses the same tables
        cs_tok = field(row, "calibrated_sensor_token", "sample_data")
        if not isinstance(cs_tok, str) or cs_tok not in channel_of_calib:
            ref(calibs, cs_tok, "calibrated_sensor", f"sample_data {row.get('token')!r}")
        key = row.get("is_key_frame", False)
        if not isinstance(key, bool):
            raise OccDataError(f"sample_data.json: row {row.get('token')!r} is_key_frame is not true/false "
                               f"({short(key)})")
        if not key and not sweeps:
            return False
        channel = channel_of_calib[cs_tok]
        return channel in wanted and (key or modalities.get(channel) == "lidar")

    return keep


def _check_links(sample_data: ColumnTable, every: TokenSet) -> None:
    """Every kept sample_data row has `prev` and `next`, each "" or a row of sample_data.json (kept or
    not); where both ends are kept, the two links agree. Checked on the tokens' hashes, all rows at once;
    a row that fails is found again in file order for the message."""
    n = len(sample_data)
    for key in ("prev", "next"):  # a missing or non-string link: the first such row, by name
        for pos in sample_data.positions():
            value = sample_data.get_at(pos, key, _MISSING)
            if type(value) is not str:
                link(sample_data.row_at(pos), key, "sample_data")
    tok_h = sample_data.token_hashes()
    link_h = {key: sample_data.hashes_of(key) for key in ("prev", "next")}
    target = {key: sample_data.positions_of_hashes(h) for key, h in link_h.items()}
    empty = hash("")
    for key in ("prev", "next"):
        outside = (link_h[key] != empty) & (target[key] < 0)
        missing = np.flatnonzero(outside)[~every.has_hashes(link_h[key][outside])]
        if len(missing):
            pos = int(missing[0])
            raise OccDataError(f"dangling token: sample_data {sample_data.value_at(pos, 'token')!r}.{key} refers "
                               f"to sample_data {sample_data.value_at(pos, key)!r}, not in sample_data.json")
    back = {"prev": "next", "next": "prev"}
    bad = np.zeros(n, dtype=bool)
    for key in ("prev", "next"):
        t = target[key]
        inside = t >= 0
        bad[inside] |= link_h[back[key]][t[inside]] != tok_h[inside]
    for pos in np.flatnonzero(bad)[:1]:
        sd = sample_data.row_at(int(pos))
        for key in ("prev", "next"):
            other = sample_data.get(sd[key])
            if other is not None and other[back[key]] != sd["token"]:
                raise OccDataError(f"sample_data.json: row {sd['token']!r}.{key} is {sd[key]!r}, but that row's "
                                   f"{back[key]} is {other[back[key]]!r}")


def _keyframes_by_sample(sample_data: ColumnTable, samples: ColumnTable, channel_of_calib: dict[str, str]) -> Keyframes:
    """Per sample and channel its keyframe sample_data row (one per channel)."""
    channels = tuple(sorted(set(channel_of_calib.values())))
    code = {c: i for i, c in enumerate(channels)}
    out = np.full((len(samples), len(channels)), -1, dtype=np.int32)
    for pos in sample_data.positions():
        if not sample_data.get_at(pos, "is_key_frame", False):
            continue
        sd = sample_data.row_at(pos)
        s_tok = field(sd, "sample_token", "sample_data")
        s_pos = samples.position(s_tok)
        if s_pos < 0:
            ref(samples, s_tok, "sample", f"sample_data {sd['token']!r}")
        channel = channel_of_calib[sd["calibrated_sensor_token"]]
        if out[s_pos, code[channel]] >= 0:
            raise OccDataError(f"sample {s_tok!r} has two keyframe {channel} records in sample_data.json")
        out[s_pos, code[channel]] = pos
    return Keyframes(channels, out)


def load_nuscenes(
    root: Path | str, version: str | None = None, check_files: bool = False, sweeps: bool = False,
    rig: RigChoice | None = None, splits: SplitChoice | None = None,
) -> NuScenesDataset:
    """Read `<root>/<version>/*.json` into keyframe records.

    Scenes come in table order, samples per scene in time order (following `next` links from
    `first_sample_token`). Each scene gets a split (`SplitChoice`): the split file's when `splits`
    names one, else the official one for nuScenes scene names (mini_train/mini_val for v1.0-mini), else
    a `split=NAME` tag in its description, else `splits.unlisted` (default "auto": train, one scene in
    five val, by a hash of its name). Scenes a split file names that the tables do not hold are noted.
    With `check_files`, every keyframe sensor file must be a readable regular file.
    `NuScenesDataset.root` is `dataset_root(root)` and every record path is that root joined with the
    row's filename: symlinks (a symlinked root included) are kept, not resolved.

    The rig (cameras, LiDARs, the reference LiDAR) comes from the tables (`resolve_rig`), narrowed by
    `rig`; the sensors not used are named in `NuScenesDataset.rig.left_out`. Timestamps written as
    floats (Lyft) are rounded to the nearest microsecond.

    With `sweeps`, the non-keyframe LiDAR rows are read too: each keyframe gets, per LiDAR, the sweeps
    that its `prev` links pass through before reaching the previous keyframe's row of that LiDAR (the
    scene's first keyframe: until `prev` is ""), nearest first. Their files are not checked
    (nuScenes' keyframe-only download ships none). A link to a token that is not a row of the same LiDAR, a
    `prev`/`next` pair that disagree, a row of another scene, a chain that reaches another keyframe
    or ends before the previous one, or a cycle, is an `OccDataError` naming the rows.

    Raises `OccDataError` (one line, naming the file or token) on a broken tree: a missing table,
    a dangling token, a duplicate token with different content, a scene whose links do not reach
    all of its samples. A problem confined to one sample's values (a non-numeric field, a file
    path outside `root`, a missing file with `check_files`) does not raise: that sample's record
    carries it in `problem` and `validate_sample` rejects it.
    """
    root = dataset_root(root)
    version = find_version(root, version)
    idx = read_tables(root, version, sweeps, rig)
    notes = list(idx.notes)
    choice = splits or SplitChoice()
    split_table = choice.table()
    samples_per_scene = Counter(idx.samples.get_at(p, "scene_token") for p in idx.samples.positions())
    scenes: list[SceneRecord] = []
    tokens: list[str] = []
    packed = PackedSamples(idx.root)
    for sc_tok, sc in idx.scenes.items():
        scene = _scene_record(idx, sc_tok, sc, samples_per_scene[sc_tok], notes, split_table, choice.unlisted)
        for i, s_tok in enumerate(scene.sample_tokens):
            # each record is made once, here (a broken tree fails now), and packed: `LazySamples`
            # makes it again from the pack when asked, without the tables
            packed.add(_sample_record(idx, s_tok, scene.name, i, _prev_keys(idx, scene, i), check_files), scene)
            tokens.append(s_tok)
        scenes.append(scene)
        idx.release()  # the scene's rows were read: their pages are the page cache's again
    packed.flush()
    absent = sorted(set(split_table) - {sc.name for sc in scenes})
    if absent:
        notes.append(f"split file {choice.file}: {len(absent)} of its scenes are not in the tables "
                     f"(first: {absent[0]!r})")
    return NuScenesDataset(
        root=root, version=version, scenes=tuple(scenes), samples=LazySamples(packed.record, tokens),
        warnings=tuple(notes), sweeps_loaded=sweeps, rig=idx.rig,
    )


def _prev_keys(idx: TableIndex, scene: SceneRecord, i: int) -> dict[str, str]:
    return _lidar_tokens(idx, scene.sample_tokens[i - 1]) if i else {}


def _lidar_tokens(idx: TableIndex, sample_token: str) -> dict[str, str]:
    """LiDAR channel -> the keyframe sample_data token of that LiDAR in a sample."""
    at = idx.keyframe_positions(sample_token)
    return {c: idx.sample_data.value_at(at[c], "token") for c in idx.rig.lidars if c in at}


def _scene_record(idx: TableIndex, sc_tok: str, sc: dict[str, Any], in_table: int, notes: list[str],
                  split_table: dict[str, str], unlisted: str) -> SceneRecord:
    """One scene with its split and its samples in `next` order; a nbr_samples mismatch goes to `notes`."""
    name = field(sc, "name", "scene")
    if not isinstance(name, str) or not usable_as_file_name(name):
        # Scene names become folder names (gts/<scene>/..., prediction output): one component each.
        raise OccDataError(
            f"scene.json: scene {sc_tok!r} has a name that is not usable as a folder name ({short(name)})"
        )
    log_token = field(sc, "log_token", "scene")
    log = ref(idx.logs, log_token, "log", f"scene {name!r}") if idx.logs is not None else {}
    chain = _scene_samples(idx, sc_tok, sc, name)
    nbr = sc.get("nbr_samples")
    if len(chain) < in_table:
        # A blank first_sample_token or a cut next link would drop samples without a word.
        raise OccDataError(
            f"scene {name!r}: only {len(chain)} of its {in_table} samples in sample.json are reachable "
            f"from first_sample_token through the next-links (nbr_samples {short(nbr)}); "
            "fix first_sample_token / next"
        )
    if nbr is not None and nbr != len(chain):
        notes.append(f"scene {name!r}: nbr_samples is {short(nbr)} but the tables hold {len(chain)} samples")
    description = str(sc.get("description", ""))
    split = split_table.get(name) or official_split(name, idx.version)
    if split is None:
        tag = SPLIT_TAG.search(description)
        split = tag.group(1) if tag else (auto_split(name) if unlisted == AUTO_SPLIT else unlisted)
    return SceneRecord(
        token=sc_tok, name=name, description=description, log_token=log_token,
        location=str(log.get("location", "")), split=split, sample_tokens=tuple(chain),
    )


def _scene_samples(idx: TableIndex, sc_tok: str, sc: dict[str, Any], name: str) -> list[str]:
    """The scene's sample tokens from `first_sample_token` along `next`, checked to stay in the
    scene, to end at `last_sample_token` and not to cycle."""
    tok = field(sc, "first_sample_token", "scene")
    chain: list[str] = []
    while tok:
        row = ref(idx.samples, tok, "sample", f"scene {name!r}" if not chain else f"sample {chain[-1]!r}.next")
        if row.get("scene_token") != sc_tok:
            raise OccDataError(f"sample {tok!r} is linked from scene {name!r} but belongs to another scene")
        if len(chain) > len(idx.samples):
            raise OccDataError(f"scene {name!r}: the sample next-links form a cycle")
        want_prev = chain[-1] if chain else ""
        if link(row, "prev", "sample") != want_prev:
            raise OccDataError(f"scene {name!r}: sample {tok!r}.prev is {short(row['prev'])}, but the scene's order "
                               f"(next-links from first_sample_token) puts {want_prev or 'nothing'!r} before it")
        chain.append(tok)
        tok = link(row, "next", "sample")
    last = field(sc, "last_sample_token", "scene")
    if chain and chain[-1] != last:
        raise OccDataError(f"scene {name!r}: the next-links end at {chain[-1]!r}, not last_sample_token {last!r}")
    return chain


def _rig_hint(rig: Rig, present: dict[str, str]) -> str:
    """What to pass when samples carry different sensors: the rig option(s) naming this sample's ones."""
    parts = []
    for option, wanted in (("--cameras", rig.cameras), ("--lidars", rig.lidars)):
        if any(c not in present for c in wanted):
            have = [c for c in wanted if c in present]
            parts.append(f"{option} {','.join(have)}" if have else f"{option} naming sensors every sample has")
    return (": the samples do not all carry the same sensors; select a rig they share with "
            f"{' and '.join(parts)} (or fewer)")


def _sample_record(
    idx: TableIndex, s_tok: str, scene_name: str, index: int, prev_keys: dict[str, str], check_files: bool
) -> SampleRecord:
    """The record of one keyframe sample; a problem with its values gives a placeholder record."""
    row = idx.samples[s_tok]
    sds = idx.keyframe_rows(s_tok)
    missing = [c for c in idx.rig.channels if c not in sds]
    if missing:
        raise OccDataError(f"sample {s_tok!r} has no keyframe sample_data for {', '.join(missing)}"
                           f"{_rig_hint(idx.rig, sds)}")
    chains = [
        _sweep_chain(idx, c, sds[c], prev_keys.get(c, ""), row["scene_token"], scene_name) if idx.sweeps else []
        for c in idx.rig.lidars
    ]
    for sd in (*sds.values(), *(sd for chain in chains for sd in chain)):
        # foreign keys first: a dangling pose is a broken tree, not a row value
        if idx.ego_poses.position(sd["ego_pose_token"]) < 0:
            ref(idx.ego_poses, sd["ego_pose_token"], "ego_pose", f"sample_data {sd['token']!r}")
    try:
        return _build_sample(idx, s_tok, row, sds, scene_name, index, chains, check_files)
    except RowProblem as exc:
        return _placeholder_sample(idx, s_tok, row, sds, scene_name, index, str(exc))


def _sweep_chain(
    idx: TableIndex, channel: str, key_sd: dict[str, Any], prev_key: str, scene_tok: str, scene_name: str
) -> list[dict[str, Any]]:
    """The non-keyframe rows of LiDAR `channel` from `key_sd` back (through `prev`) to the previous
    keyframe's row `prev_key` of that LiDAR ("" for the scene's first keyframe: to the chain's start)."""
    out: list[dict[str, Any]] = []
    cur, tok = key_sd, key_sd.get("prev", "")
    while tok and tok != prev_key:
        nxt = idx.lidar_row(tok)
        where = f"{channel} chain of scene {scene_name!r}: sample_data {cur['token']!r}.prev"
        if nxt is None or idx.channel_of_calib[nxt["calibrated_sensor_token"]] != channel:
            raise OccDataError(f"{where} is {tok!r}, not a {channel} row of sample_data.json")
        if nxt.get("is_key_frame", False):
            raise OccDataError(f"{where} reaches keyframe {tok!r}, not the previous keyframe's {channel} "
                               f"{prev_key or '(none: first keyframe)'!r}")
        if nxt.get("next", "") != cur["token"]:
            raise OccDataError(f"{where} is {tok!r}, but that row's next is {nxt.get('next', '')!r}")
        s_row = ref(idx.samples, field(nxt, "sample_token", "sample_data"), "sample", f"sample_data {tok!r}")
        if s_row.get("scene_token") != scene_tok:
            raise OccDataError(f"{where} is {tok!r}, a row of another scene (sample {nxt['sample_token']!r})")
        if len(out) >= idx.n_lidar_rows:
            raise OccDataError(f"{where}: the prev-links form a cycle")
        out.append(nxt)
        cur, tok = nxt, nxt.get("prev", "")
    if prev_key and tok != prev_key:
        raise OccDataError(f"{channel} chain of scene {scene_name!r}: the prev-links from keyframe sample_data "
                           f"{key_sd['token']!r} end at {cur['token']!r} before the previous keyframe's "
                           f"{channel} {prev_key!r}")
    return out


def _sensor_path(idx: TableIndex, sd: dict[str, Any], check_files: bool) -> Path:
    """The sample_data row's file under the root; with `check_files` it must be a regular file.
    Problems are `RowProblem`s (they stay with the sample)."""
    where = f"sample_data {sd['token']!r} filename"
    try:
        path = confined_path(idx.root, field(sd, "filename", "sample_data"), where)
    except OccDataError as exc:
        raise RowProblem(str(exc)) from None
    if check_files and not path.is_file():
        if os.path.lexists(path):  # a folder, a dangling link or a symlink loop
            raise RowProblem(f"sensor file {path} is not a readable regular file (sample_data {sd['token']!r})")
        raise RowProblem(f"missing sensor file: {path} (sample_data {sd['token']!r})")
    return path


def _ego_pose(idx: TableIndex, sd: dict[str, Any]) -> np.ndarray:
    """`(4, 4) float64` T_global_from_ego at the sample_data row's own timestamp."""
    return pose(ref(idx.ego_poses, sd["ego_pose_token"], "ego_pose", f"sample_data {sd['token']!r}"), "ego_pose")


def _timestamp(sd: dict[str, Any]) -> int:
    return timestamp_us(field(sd, "timestamp", "sample_data"), f"sample_data {sd['token']!r} timestamp")


def _calibration(idx: TableIndex, cs_token: str, channel: str | None) -> tuple[np.ndarray, np.ndarray | None]:
    """A calibrated_sensor row's `T_sensor` `(4, 4) float64` (sensor -> ego) and, for a camera
    (`channel` given), `K (3, 3) float64`: made once per row and shared, read-only, by every record
    of that sensor (a sample's records held ~2 KB of copies of them). `RowProblem`s are not cached."""
    key = (cs_token, channel is not None)
    if key not in idx.calib_cache:
        cs = idx.calibs[cs_token]
        K = None
        if channel is not None:
            where = f"calibrated_sensor {cs['token']!r} ({channel})"
            K = floats(field(cs, "camera_intrinsic", "calibrated_sensor"), (3, 3), f"{where} camera_intrinsic")
            K.setflags(write=False)
        T = pose(cs, "calibrated_sensor")
        T.setflags(write=False)
        idx.calib_cache[key] = (T, K)
    return idx.calib_cache[key]


def _camera_record(idx: TableIndex, channel: str, sd: dict[str, Any], check_files: bool) -> CameraRecord:
    T_ego_from_cam, K = _calibration(idx, sd["calibrated_sensor_token"], channel)
    sd_where = f"sample_data {sd['token']!r}"
    return CameraRecord(
        channel=channel,
        token=sd["token"],
        path=_sensor_path(idx, sd, check_files),
        K=K,
        T_ego_from_cam=T_ego_from_cam,
        T_global_from_ego=_ego_pose(idx, sd),
        timestamp=_timestamp(sd),
        width=integer(field(sd, "width", "sample_data"), f"{sd_where} width"),
        height=integer(field(sd, "height", "sample_data"), f"{sd_where} height"),
    )


def _lidar_record(idx: TableIndex, sd: dict[str, Any], check_files: bool) -> LidarRecord:
    return LidarRecord(
        channel=idx.channel_of_calib[sd["calibrated_sensor_token"]],
        token=sd["token"],
        path=_sensor_path(idx, sd, check_files),
        T_ego_from_lidar=_calibration(idx, sd["calibrated_sensor_token"], None)[0],
        T_global_from_ego=_ego_pose(idx, sd),
        timestamp=_timestamp(sd),
        sample_token=sd["sample_token"],
    )


def _build_sample(
    idx: TableIndex, s_tok: str, row: dict[str, Any], sds: dict[str, dict[str, Any]], scene_name: str,
    index: int, chains: list[list[dict[str, Any]]], check_files: bool,
) -> SampleRecord:
    cams = tuple(_camera_record(idx, channel, sds[channel], check_files) for channel in idx.rig.cameras)
    lidars = [_lidar_record(idx, sds[channel], check_files) for channel in idx.rig.lidars]
    sweeps = [tuple(_lidar_record(idx, sd, check_files=False) for sd in chain) for chain in chains]
    return SampleRecord(
        token=s_tok,
        scene_token=field(row, "scene_token", "sample"),
        scene_name=scene_name,
        index_in_scene=index,
        timestamp=timestamp_us(field(row, "timestamp", "sample"), f"sample {s_tok!r} timestamp"),
        prev=row.get("prev", ""),
        next=row.get("next", ""),
        cameras=cams,
        lidar=lidars[0],
        sweeps=sweeps[0],  # sweep files are not checked: nuScenes' keyframe download ships none
        extra_lidars=tuple(lidars[1:]),
        extra_sweeps=tuple(sweeps[1:]),
    )


def _placeholder_sample(
    idx: TableIndex, s_tok: str, row: dict[str, Any], sds: dict[str, dict[str, Any]], scene_name: str, index: int,
    problem: str,
) -> SampleRecord:
    """A record of NaN placeholders carrying `problem` (`validate_sample` rejects it)."""
    nan4 = np.full((4, 4), np.nan)
    cams = tuple(
        CameraRecord(channel=c, token=sds[c]["token"], path=idx.root, K=np.full((3, 3), np.nan),
                     T_ego_from_cam=nan4, T_global_from_ego=nan4, timestamp=0, width=0, height=0)
        for c in idx.rig.cameras
    )
    lidars = [LidarRecord(channel=c, token=sds[c]["token"], path=idx.root, T_ego_from_lidar=nan4,
                          T_global_from_ego=nan4, timestamp=0, sample_token=s_tok) for c in idx.rig.lidars]
    ts = row.get("timestamp")
    return SampleRecord(
        token=s_tok, scene_token=row["scene_token"], scene_name=scene_name, index_in_scene=index,
        timestamp=ts if isinstance(ts, int) and not isinstance(ts, bool) and ts >= 0 else 0,
        prev=row.get("prev", ""), next=row.get("next", ""), cameras=cams, lidar=lidars[0], problem=problem,
        extra_lidars=tuple(lidars[1:]), extra_sweeps=tuple(() for _ in lidars[1:]),
    )


def load_lidar_points(path: Path | str) -> np.ndarray:
    """A LiDAR sweep: `(N, 5) float32` x, y, z, intensity, ring (lidar frame). `.pcd.bin` / `.bin`:
    raw float32 x 5 (nuScenes, Lyft); `.pcd`: a PCD file of any encoding (`pointfiles.read_pcd`,
    which also gives the per-point timestamps a file may have)."""
    path = Path(path)
    if is_pcd(path):
        return read_pcd(path).points
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise OccDataError(f"missing sensor file: {path}") from None
    except OSError as exc:  # a folder, a symlink loop, no permission, an I/O error
        raise OccDataError(f"cannot read sensor file {path}: {exc.strerror or exc}") from None
    if len(raw) == 0 or len(raw) % 20:
        raise OccDataError(f"corrupt LiDAR file {path}: {len(raw)} bytes is not a positive multiple of 20")
    points = np.frombuffer(raw, dtype=np.float32).reshape(-1, 5)
    if not np.isfinite(points[:, :3]).all():
        raise OccDataError(f"corrupt LiDAR file {path}: non-finite coordinates")
    return points


def validate_sample(sample: SampleRecord) -> None:
    """Raise `OccDataError` if the sample's rows were unusable (`problem`), or any calibration or
    pose is non-finite or not rigid, or an intrinsic matrix or image size is invalid."""
    if sample.problem:
        raise OccDataError(f"sample {sample.token!r}: {sample.problem}")

    def check_rigid(T: np.ndarray, what: str) -> None:
        if not np.isfinite(T).all():
            raise OccDataError(f"sample {sample.token!r}: {what} has NaN/inf values")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise OccDataError(f"sample {sample.token!r}: {what} rotation is not orthonormal")

    for cam in sample.cameras:
        check_rigid(cam.T_ego_from_cam, f"{cam.channel} calibration")
        check_rigid(cam.T_global_from_ego, f"{cam.channel} ego pose")
        K = cam.K
        if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise OccDataError(f"sample {sample.token!r}: {cam.channel} intrinsics are invalid")
        if cam.width <= 0 or cam.height <= 0:
            raise OccDataError(f"sample {sample.token!r}: {cam.channel} image size {cam.width}x{cam.height}")
    for lidar in sample.lidars:
        check_rigid(lidar.T_ego_from_lidar, f"{lidar.channel} calibration")
        check_rigid(lidar.T_global_from_ego, f"{lidar.channel} ego pose")
