"""3D box annotations (`instance`, `sample_annotation`) and boxes at any LIDAR_TOP time
(docs/design.md#labels-from-lidar).

Frames: a box's pose is box -> global. Box frame (the devkit's `Box`): origin at the box centre,
x along the length (forward), y along the width (left), z up; `size_wlh` is (width, length, height).

`boxes_at` / `boxes_for_lidar` reproduce the official devkit's `NuScenes.get_boxes(sample_data)`:
a keyframe (or a sample without `prev`) gets its sample's boxes as stored; a non-keyframe sweep,
filed under the NEXT keyframe's sample, gets that sample's boxes, each interpolated towards the same
instance's box in the previous sample (translation linearly, rotation by slerp with pyquaternion's
shortest-path rule) at the sweep's time fraction, clamped to [0, 1]. A box whose instance is not in
the previous sample is kept as it is; instances only in the previous sample are dropped.
"""

from __future__ import annotations

from array import array
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from occdata.errors import OccDataError
from occdata.geometry import transform_from_pose
from occdata.nuscenes.columns import ColumnTable, HashIndex
from occdata.nuscenes.records import LidarRecord, NuScenesDataset
from occdata.nuscenes.rows import RowProblem, field, floats, integer, ref, short, timestamp_us
from occdata.nuscenes.spill import BUCKETS, BucketSpill, Spill
from occdata.nuscenes.spill import TEXT_ERRORS as _TEXT
from occdata.nuscenes.tables import TokenSet, iter_table_rows, load_table

__all__ = ["MOVING_TRAVEL_M", "Annotations", "BoxRecord", "box_velocity", "boxes_for_lidar", "load_annotations",
           "moving_instances", "slerp_wxyz"]


@dataclass(frozen=True, eq=False, slots=True)
class BoxRecord:
    """One annotated 3D box (a `sample_annotation` row), or that box moved to another time.

    `center_global (3,) float64` box centre in global; `size_wlh (3,) float64` width, length,
    height (m); `rotation_wxyz (4,) float64` box -> global rotation as stored (or interpolated);
    `timestamp` (us): the sample's, or the sweep time the box was interpolated to.
    """

    token: str  # sample_annotation token
    instance_token: str
    sample_token: str
    category: str  # category name, e.g. "vehicle.car"
    center_global: np.ndarray
    size_wlh: np.ndarray
    rotation_wxyz: np.ndarray
    timestamp: int
    num_lidar_pts: int
    prev: str = ""  # sample_annotation token of the instance's previous box ("" at a track start)
    next: str = ""  # ... and of its next box ("" at a track end)

    def T_global_from_box(self) -> np.ndarray:
        """`(4, 4) float64`: box frame (x forward along the length, y left, z up, origin at the
        centre) -> global. The quaternion is normalised first, as pyquaternion does."""
        return transform_from_pose(self.center_global, self.rotation_wxyz)


@dataclass(frozen=True, eq=False)
class Annotations:
    """The boxes of a version folder, by sample, and each instance's category name."""

    boxes_by_sample: Mapping[str, tuple[BoxRecord, ...]]  # sample token -> its boxes (table order): `PackedBoxes`
    instance_category: dict[str, str]  # instance token -> category name

    def for_samples(self, sample_tokens: Collection[str]) -> Annotations:
        """The boxes of `sample_tokens` alone, and their instances' categories (a task's slice)."""
        boxes = {t: self.boxes_by_sample[t] for t in sample_tokens if t in self.boxes_by_sample}
        instances = dict.fromkeys(b.instance_token for bs in boxes.values() for b in bs)
        return Annotations(boxes_by_sample=boxes, instance_category={k: self.instance_category[k] for k in instances})

    def boxes_at(
        self, sample_token: str, prev_sample_token: str, t0_us: int, t1_us: int, t_us: int
    ) -> tuple[BoxRecord, ...]:
        """The boxes at time `t_us` of a sweep filed under `sample_token` (the devkit's `get_boxes`).

        `prev_sample_token` is that sample's `prev`; pass "" for a keyframe (or a sample without
        `prev`): the sample's boxes come back as stored. Otherwise `t0_us`, `t1_us` are the previous
        and the current sample's timestamps (t0 < t1) and each box whose instance also has a box in
        the previous sample is interpolated at `clamp(t_us, t0, t1)`; every returned box then
        carries `timestamp = t_us`. A sample without boxes gives ().
        """
        current = self.boxes_by_sample.get(sample_token, ())
        if not prev_sample_token:
            return current
        if not t1_us > t0_us:
            raise OccDataError(
                f"sample {sample_token!r}: timestamp {t1_us} is not after its prev {prev_sample_token!r} ({t0_us})"
            )
        prev_of = {b.instance_token: b for b in self.boxes_by_sample.get(prev_sample_token, ())}  # last wins
        t = max(t0_us, min(t1_us, t_us))
        return tuple(_interpolated(prev_of.get(b.instance_token), b, t0_us, t1_us, t, t_us) for b in current)


    def box_velocities(self, max_time_diff_s: float = 1.5) -> dict[str, np.ndarray]:
        """sample_annotation token -> `v_global (3,) float64` m/s, `box_velocity` of every box with the
        neighbours its prev / next name (a scene's slice holds its instances' whole tracks: an
        instance never leaves its scene). NaN where the devkit gives NaN."""
        by_token = {b.token: b for boxes in self.boxes_by_sample.values() for b in boxes}
        return {tok: box_velocity(b, by_token.get(b.prev), by_token.get(b.next), max_time_diff_s)
                for tok, b in by_token.items()}


def box_velocity(box: BoxRecord, prev: BoxRecord | None, next_: BoxRecord | None,
                 max_time_diff_s: float = 1.5) -> np.ndarray:
    """`v_global (3,) float64` m/s of `box`, the devkit's `NuScenes.box_velocity`: the centre difference
    between the instance's previous and next boxes (`box` itself standing in for a missing one) over
    their sample timestamps. NaN x 3 with neither neighbour, or when the time span exceeds
    `max_time_diff_s` (doubled when both neighbours exist, as the span is then two steps)."""
    if prev is None and next_ is None:
        return np.full(3, np.nan)
    first = prev if prev is not None else box
    last = next_ if next_ is not None else box
    # Each timestamp in seconds first, then the difference: the devkit's rounding (~1e-7 relative), so
    # that its values are met to the bit.
    dt_s = 1e-6 * last.timestamp - 1e-6 * first.timestamp
    if dt_s > (2 * max_time_diff_s if prev is not None and next_ is not None else max_time_diff_s):
        return np.full(3, np.nan)
    return (np.asarray(last.center_global, np.float64) - np.asarray(first.center_global, np.float64)) / dt_s


def _link(token: Any) -> str:
    return token if isinstance(token, str) else ""


def _interpolated(prev: BoxRecord | None, cur: BoxRecord, t0: int, t1: int, t: int, t_us: int) -> BoxRecord:
    """`cur` moved to time `t` (t0 <= t <= t1) along the track from `prev`; as is without `prev`."""
    if prev is None:
        return replace(cur, timestamp=t_us)
    if t == t1:
        center = cur.center_global.copy()  # numpy's interp returns the end point exactly
    else:
        center = (cur.center_global - prev.center_global) / (t1 - t0) * (t - t0) + prev.center_global
    rotation = slerp_wxyz(prev.rotation_wxyz, cur.rotation_wxyz, (t - t0) / (t1 - t0))
    center.flags.writeable = rotation.flags.writeable = False  # like the loaded records' arrays
    return replace(cur, center_global=center, rotation_wxyz=rotation, timestamp=t_us)


def _unit(q: np.ndarray) -> np.ndarray:
    """pyquaternion's `_fast_normalise`: a Pade step near unit length, else the exact norm."""
    mag2 = float(np.dot(q, q))
    if abs(1.0 - mag2) < 1e-14 or mag2 == 0.0:
        return q
    mag = (1.0 + mag2) / 2.0 if abs(1.0 - mag2) < 2.107342e-08 else np.sqrt(mag2)
    return q / mag


def slerp_wxyz(q0_wxyz: np.ndarray, q1_wxyz: np.ndarray, amount: float) -> np.ndarray:
    """Spherical linear interpolation of two `(4,)` wxyz quaternions, `(4,) float64` unit result.

    Same rule as pyquaternion's `Quaternion.slerp`: inputs normalised, `amount` clipped to [0, 1],
    `q0` negated when the dot product is negative (the shorter arc), a normalised linear blend when
    the dot product exceeds 0.9995.
    """
    q0 = _unit(np.asarray(q0_wxyz, dtype=np.float64))
    q1 = _unit(np.asarray(q1_wxyz, dtype=np.float64))
    amount = float(np.clip(amount, 0.0, 1.0))
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q0, dot = -q0, -dot
    if dot > 0.9995:
        return _unit(q0 + amount * (q1 - q0))
    theta_0 = np.arccos(dot)
    sin_theta_0 = np.sin(theta_0)
    theta = theta_0 * amount
    s0 = np.cos(theta) - dot * np.sin(theta) / sin_theta_0
    s1 = np.sin(theta) / sin_theta_0
    return _unit(s0 * q0 + s1 * q1)


def boxes_for_lidar(
    ann: Annotations, dataset: NuScenesDataset, sample_index: int, lidar: LidarRecord
) -> tuple[BoxRecord, ...]:
    """The boxes at a LIDAR_TOP sweep's time, as the devkit's `get_boxes(lidar.token)` gives them.

    `lidar` is `dataset.samples[sample_index].lidar` (the keyframe: its sample's boxes as stored) or
    one of that sample's `sweeps` (read with `sweeps=True`): interpolated between the sample that
    the sweep is filed under (`lidar.sample_token`) and that sample's `prev`. Anything else is an
    `OccDataError`.
    """
    sample = dataset.samples[sample_index]
    if lidar.token == sample.lidar.token:
        return ann.boxes_at(sample.token, "", 0, 0, lidar.timestamp)
    if not any(sw.token == lidar.token for sw in sample.sweeps):
        raise OccDataError(
            f"sample_data {lidar.token!r} is neither the LIDAR_TOP keyframe nor a sweep of sample {sample.token!r}"
            + ("" if dataset.sweeps_loaded else " (the tables were read without sweeps=True)")
        )
    try:
        owner = dataset.sample(lidar.sample_token or sample.token)
        prev = dataset.sample(owner.prev) if owner.prev else None
    except KeyError as exc:
        raise OccDataError(f"sample_data {lidar.token!r}: sample {exc.args[0]!r} is not in the dataset") from None
    if prev is None:
        return ann.boxes_at(owner.token, "", 0, 0, lidar.timestamp)
    return ann.boxes_at(owner.token, prev.token, prev.timestamp, owner.timestamp, lidar.timestamp)


_BOX = np.dtype([("translation", "<f8", (3,)), ("size", "<f8", (3,)), ("rotation", "<f8", (4,)),
                 ("timestamp", "<i8"), ("num_lidar_pts", "<i8")])
_TEXTS = 5  # a box's texts: token, instance_token, sample_token, prev, next
_BOX_HEAD = _BOX.itemsize + 4 * _TEXTS  # a box blob's fixed part: its numbers, then its texts' byte lengths


def _box_blob(numbers: np.void, texts: tuple[str, ...]) -> bytes:
    """One box as bytes: its `_BOX` numbers, the byte lengths of its `_TEXTS` texts (int32), the texts."""
    encoded = [t.encode("utf-8", _TEXT) for t in texts]
    return b"".join((numbers.tobytes(), np.array([len(e) for e in encoded], dtype="<i4").tobytes(), *encoded))


def _parse_boxes(blob: bytes) -> Iterator[tuple[np.ndarray, list[str]]]:
    """The boxes of concatenated box blobs: each one's numbers (a read-only `_BOX` array of one) and texts."""
    at = 0
    while at < len(blob):
        numbers = np.frombuffer(blob, _BOX, 1, at)
        lens = np.frombuffer(blob, "<i4", _TEXTS, at + _BOX.itemsize).tolist()
        at += _BOX_HEAD
        texts = []
        for n in lens:
            texts.append(blob[at:at + n].decode("utf-8", _TEXT))
            at += n
        yield numbers, texts


class PackedBoxes(Mapping[str, tuple[BoxRecord, ...]]):
    """sample token -> its boxes (table order), each `BoxRecord` made when asked from the sample's blob
    in a `Spill` (an unnamed temporary file): in memory a sample with boxes keeps its blob's end and an
    index entry (~24 bytes), not its boxes (~0.8 KB each as Python objects; nuScenes has ~35 a
    keyframe). Iteration gives the samples in the order of their first box. Pickled (a task's slice),
    it becomes a dict. A sample's blob is its boxes' blobs (`_box_blob`), one after the other."""

    def __init__(self, spill: Spill, sample_hashes: np.ndarray, instance_category: dict[str, str]) -> None:
        self._spill, self._category = spill, instance_category
        self._index = HashIndex(sample_hashes)

    def __len__(self) -> int:
        return len(self._spill)

    def __iter__(self) -> Iterator[str]:
        return (self._sample_of(k) for k in range(len(self)))

    def __getitem__(self, sample_token: str) -> tuple[BoxRecord, ...]:
        if isinstance(sample_token, str):
            for k in self._index.candidates(sample_token):
                if self._sample_of(k) == sample_token:
                    return self._boxes(k)
        raise KeyError(sample_token)

    def _sample_of(self, k: int) -> str:
        """Blob k's sample token, from its first box's texts alone (no box made)."""
        blob = self._spill.get(k)
        token_n, instance_n, sample_n = np.frombuffer(blob, "<i4", 3, _BOX.itemsize).tolist()
        at = _BOX_HEAD + token_n + instance_n
        return blob[at:at + sample_n].decode("utf-8", _TEXT)

    def _boxes(self, k: int) -> tuple[BoxRecord, ...]:
        out = []
        for numbers, (token, instance, sample, prev, nxt) in _parse_boxes(self._spill.get(k)):
            b = numbers[0]  # views of a read-only buffer: the records' arrays are read-only
            out.append(BoxRecord(
                token=token, instance_token=instance, sample_token=sample, category=self._category[instance],
                center_global=b["translation"], size_wlh=b["size"], rotation_wxyz=b["rotation"],
                timestamp=int(b["timestamp"]), num_lidar_pts=int(b["num_lidar_pts"]), prev=prev, next=nxt))
        return tuple(out)

    def __reduce__(self) -> tuple[Any, ...]:
        return (dict, (dict(self.items()),))


def load_annotations(root: Path, version: str, sample_tokens: Collection[str] | None = None) -> Annotations:
    """Read `<root>/<version>/{sample_annotation,instance,category,sample}.json` into `Annotations`.

    With `sample_tokens`, only those samples' boxes are kept (interpolating a sweep needs its sample
    and that sample's `prev`). No instance.json and no sample_annotation.json (a test split): empty
    `Annotations`. The box arrays are read-only.

    The boxes are streamed (`_BoxReader`): checked a chunk of rows at a time and written to a spill
    file, their hashes in bucket files; what stays in memory is 8 bytes a box and one bucket.

    Raises `OccDataError`, one line naming the table and token, on a broken tree: one of the two
    tables without the other, a sample_token / instance_token / category_token that is not in its
    table, prev/next naming a token not in sample_annotation.json or a box of another instance,
    prev/next links that disagree, a token twice with different content, a missing field, a
    non-numeric, non-finite or wrongly sized translation, size or rotation, a size that is not
    positive, a rotation that is not a unit quaternion, a non-integer num_lidar_pts.
    """
    vdir = Path(root) / version
    ann_path, inst_path = vdir / "sample_annotation.json", vdir / "instance.json"
    if not ann_path.is_file() and not inst_path.is_file():
        return Annotations(boxes_by_sample={}, instance_category={})
    for path in (ann_path, inst_path, vdir / "category.json", vdir / "sample.json"):
        if not path.is_file():
            raise OccDataError(f"missing table: {path} (needed with {ann_path.name} / {inst_path.name})")
    categories = load_table(vdir / "category.json")
    instances = load_table(inst_path)
    instance_category = {tok: _category_name(categories, tok, row) for tok, row in instances.items()}
    reader = _BoxReader(load_table(vdir / "sample.json", columns=True), instance_category)
    reader.read(ann_path, None if sample_tokens is None else set(sample_tokens))
    return Annotations(boxes_by_sample=reader.packed(), instance_category=instance_category)


_FIELDS = ("sample_token", "instance_token")
_VALUES = ("translation", "size", "rotation", "num_lidar_pts")
_CHUNK = 8192  # rows checked together (vectorised number checks), then written


_TRACK = np.dtype([("k", "<i8"), ("token", "<i8"), ("instance", "<i8"), ("prev", "<i8"), ("next", "<i8")])
_GROUP = np.dtype([("k", "<i8"), ("sample", "<i8")])
_LOOKUP = np.dtype([("k", "<i8"), ("link", "<i8"), ("hash", "<i8")])  # a link to look up in the token sets
_LINKS = (("prev", "next"), ("next", "prev"))  # a link and the one that must point back
_BUCKET_ROWS = 1 << 16  # box hashes held in memory before they go to their bucket files


class _BoxReader:
    """The rows of sample_annotation.json, streamed: each chunk of kept rows is checked (references,
    numbers) and each box written to a spill file as it comes (box k: the k-th kept row). The checks that
    need every row (duplicates, tracks) and the regrouping by sample run on the boxes' hashes, kept on
    disk in buckets: by instance for the tracks (a track's boxes share a bucket), by sample for
    `packed()`. Memory holds 8 bytes a box (its blob's end) and one bucket at a time (1/64 of the boxes),
    not ~60 bytes a box."""

    def __init__(self, sample_rows: ColumnTable, instance_category: dict[str, str]) -> None:
        self._sample_rows, self._category = sample_rows, instance_category
        self._sample_ts: dict[str, int] = {}  # per sample with boxes: its timestamp (us)
        self._rows = Spill()  # box k's blob
        self._by_instance = BucketSpill(_TRACK, "instance", _BUCKET_ROWS)
        self._by_sample = BucketSpill(_GROUP, "sample", _BUCKET_ROWS)
        self._every = TokenSet()  # every row's token
        self._kept = TokenSet()  # the kept boxes' tokens
        self._n = 0
        self._dropped: set[int] = set()  # later identical copies of a repeated token

    def read(self, path: Path, wanted: set[str] | None) -> None:
        chunk: list[dict[str, Any]] = []
        for raw in iter_table_rows(path):
            token = raw.get("token")
            if not isinstance(token, str) or not token:
                raise OccDataError(f"malformed table {path}: a row has no string 'token' field")
            self._every.add(token)
            sample = raw.get("sample_token")
            if wanted is not None and not (isinstance(sample, str) and sample in wanted):
                continue
            chunk.append({"token": token, **{k: field(raw, k, "sample_annotation") for k in (*_FIELDS, *_VALUES)},
                          "prev": raw.get("prev", ""), "next": raw.get("next", "")})
            if len(chunk) == _CHUNK:
                self._add(chunk)
                chunk = []
        self._add(chunk)
        self._rows.flush()
        self._drop_copies(path)
        self._check_tracks()

    def _add(self, rows: list[dict[str, Any]]) -> None:
        """Check a chunk of rows and write their boxes and their hashes."""
        if not rows:
            return
        boxes = np.zeros(len(rows), dtype=_BOX)
        boxes["timestamp"] = [self._timestamp(r) for r in rows]
        tokens = [r["token"] for r in rows]
        for key in ("translation", "size", "rotation"):
            boxes[key] = _numbers(tokens, [r[key] for r in rows], key)
        boxes["num_lidar_pts"] = _counts(tokens, [r["num_lidar_pts"] for r in rows])
        track, group = np.zeros(len(rows), _TRACK), np.zeros(len(rows), _GROUP)
        track["k"] = group["k"] = np.arange(self._n, self._n + len(rows))
        self._n += len(rows)
        for i, (r, b) in enumerate(zip(rows, boxes, strict=True)):
            links = [_track_link(r, link) for link in ("prev", "next")]
            texts = (r["token"], r["instance_token"], r["sample_token"], *links)
            self._rows.add(_box_blob(b, texts))
            self._kept.add(r["token"])
            track[i] = (track["k"][i], hash(texts[0]), hash(texts[1]), hash(texts[3]), hash(texts[4]))
            group["sample"][i] = hash(texts[2])
        self._by_instance.add(track)
        self._by_sample.add(group)

    def _timestamp(self, row: dict[str, Any]) -> int:
        """Check the row's instance and sample exist; the sample's timestamp (us)."""
        instance, sample = row["instance_token"], row["sample_token"]
        src = f"sample_annotation {row['token']!r}"
        if not isinstance(instance, str) or instance not in self._category:
            raise OccDataError(f"dangling token: {src} refers to instance {instance!r}, not in instance.json")
        ts = self._sample_ts.get(sample) if isinstance(sample, str) else None
        if ts is None:
            sample_row = ref(self._sample_rows, sample, "sample", src)
            try:
                ts = timestamp_us(field(sample_row, "timestamp", "sample"), f"sample {sample!r} timestamp")
            except RowProblem as exc:
                raise OccDataError(f"sample.json: {exc}") from None
            self._sample_ts[sample] = ts
        return ts

    def _box(self, k: int) -> tuple[bytes, list[str]]:
        """Box k's blob and texts (token, instance, sample, prev, next)."""
        blob = self._rows.get(k)
        return blob, next(_parse_boxes(blob))[1]

    def _boxes_with_token_hash(self, hashes: np.ndarray) -> list[int]:
        """The boxes (k, ascending) whose token hash is one of `hashes` `(m,) int64` (one pass over the
        buckets: for the rare rows that repeat a token or fail a check)."""
        out: list[int] = []
        for b in range(BUCKETS):
            rows = self._by_instance.bucket(b)
            out.extend(rows["k"][np.isin(rows["token"], hashes)].tolist())
        return sorted(out)

    def _drop_copies(self, path: Path) -> None:
        """A token kept twice: the later identical copies are dropped; differing copies are an error."""
        repeated = self._every.repeated()
        if not repeated:
            return
        first: dict[str, bytes] = {}
        for k in self._boxes_with_token_hash(np.fromiter(repeated, np.int64, len(repeated))):
            blob, texts = self._box(k)
            seen = first.setdefault(texts[0], blob)
            if seen is not blob:
                if seen != blob:
                    raise OccDataError(f"duplicate token in {path.name}: {texts[0]!r} appears twice with different "
                                       "content")
                self._dropped.add(k)

    def _check_tracks(self) -> None:
        """Every prev/next names a box of the table, of the same instance, that links back. On the
        hashes, one instance bucket at a time (a box's track partners share its bucket); a link to no
        box of its bucket is then looked up in the token sets, one hash bucket at a time (a kept box of
        another bucket is a box of another instance; no token of the table is a dangling link). The
        rows that may be wrong are read back and named, in row order, prev before next."""
        suspects: list[tuple[int, int]] = []  # (k, 0 for prev / 1 for next)
        elsewhere = BucketSpill(_LOOKUP, "hash", _BUCKET_ROWS)
        dropped = np.fromiter(self._dropped, np.int64, len(self._dropped))
        for b in range(BUCKETS):
            rows = self._by_instance.bucket(b)
            if len(dropped):  # later identical copies are no box: not checked, "" is no box's token
                rows = rows[~np.isin(rows["k"], dropped)]
            for j, (link, back) in enumerate(_LINKS):
                wrong, away = self._track_faults(rows, link, back)
                suspects.extend((k, j) for k in rows["k"][wrong].tolist())
                lookup = np.zeros(int(away.sum()), _LOOKUP)
                lookup["k"], lookup["link"], lookup["hash"] = rows["k"][away], j, rows[link][away]
                elsewhere.add(lookup)
        for b in range(BUCKETS):  # each token set read once, a bucket at a time
            rows = elsewhere.bucket(b)
            if len(rows):
                bad = self._kept.has_hashes(rows["hash"]) | ~self._every.has_hashes(rows["hash"])
                suspects.extend(zip(rows["k"][bad].tolist(), rows["link"][bad].tolist(), strict=True))
        for k, j in sorted(suspects):
            self._name_track_fault(k, *_LINKS[j])

    @staticmethod
    def _track_faults(rows: np.ndarray, link: str, back: str) -> tuple[np.ndarray, np.ndarray]:
        """For the rows (`_TRACK`, one instance bucket), two `(len(rows),) bool`: whose `link` names a box
        of the bucket that is of another instance or does not link back (wrong), and whose `link` names
        no box of the bucket (away: a box of another instance, outside the samples read, or none)."""
        linked = rows[link]
        has = linked != hash("")
        order = np.argsort(rows["token"], kind="stable")
        sorted_h = rows["token"][order]
        i = np.minimum(np.searchsorted(sorted_h, linked), max(len(sorted_h) - 1, 0))
        found = has & (sorted_h[i] == linked) if len(sorted_h) else np.zeros(len(linked), bool)
        q = order[i] if len(order) else np.zeros(len(linked), np.int64)
        wrong = found & ((rows["instance"][q] != rows["instance"]) | (rows[back][q] != rows["token"]))
        return wrong, has & ~found

    def _name_track_fault(self, k: int, link: str, back: str) -> None:
        """Raise the error for box k's `link`, found on the hashes, if the texts confirm it."""
        _, (token, instance, _, prev, nxt) = self._box(k)
        other = prev if link == "prev" else nxt
        where = f"sample_annotation.json: row {token!r} {link}"
        q = next((p for p in self._boxes_with_token_hash(np.array([hash(other)], np.int64))
                  if p not in self._dropped and self._box(p)[1][0] == other), -1)
        if q < 0:
            if other not in self._every:
                raise OccDataError(f"{where} {other!r} is not in sample_annotation.json")
            return  # outside the selected samples
        _, (_, other_instance, _, other_prev, other_next) = self._box(q)
        if other_instance != instance:
            raise OccDataError(f"{where} {other!r} is a box of another instance")
        other_back = other_prev if back == "prev" else other_next
        if other_back != token:
            raise OccDataError(f"{where} is {other!r}, but that row's {back} is {other_back!r}")

    def packed(self) -> PackedBoxes:
        """The boxes regrouped by sample (samples in the order of their first box, boxes in table order):
        one sample bucket at a time into a first spill, then copied into sample order."""
        grouped, first_k, hashes = Spill(), array("q"), array("q")
        for b in range(BUCKETS):
            rows = self._by_sample.bucket(b)  # in k order
            if not len(rows):
                continue
            order = np.argsort(rows["sample"], kind="stable")
            starts = np.flatnonzero(np.r_[True, np.diff(rows["sample"][order]) != 0])
            ends = np.r_[starts[1:], len(order)]
            for s0, s1 in zip(starts, ends, strict=True):
                by_sample: dict[str, list[bytes]] = {}  # one entry, unless two samples share a 64-bit hash
                first: dict[str, int] = {}
                for k in rows["k"][order[s0:s1]].tolist():
                    if k not in self._dropped:
                        blob, texts = self._box(k)
                        by_sample.setdefault(texts[2], []).append(blob)
                        first.setdefault(texts[2], k)
                for sample, blobs in by_sample.items():
                    grouped.add(b"".join(blobs))
                    first_k.append(first[sample])
                    hashes.append(hash(sample))
        grouped.flush()
        out = Spill()
        ranks = np.argsort(np.frombuffer(first_k, np.int64), kind="stable") if first_k else np.zeros(0, np.int64)
        for g in ranks.tolist():
            out.add(grouped.get(g))
        out.flush()
        self._rows = Spill()  # the per-box files are closed
        self._by_instance = self._by_sample = None  # type: ignore[assignment]
        sample_h = np.frombuffer(hashes, np.int64)[ranks] if hashes else np.zeros(0, np.int64)
        return PackedBoxes(out, sample_h, self._category)


def _track_link(row: dict[str, Any], link: str) -> str:
    """A row's prev/next as text ("" for none); a value that is not a string names no box of the table."""
    value = row[link]
    if not value:
        return ""
    if not isinstance(value, str):
        raise OccDataError(f"sample_annotation.json: row {row['token']!r} {link} {value!r} is not in "
                           "sample_annotation.json")
    return value


_WIDTH = {"translation": 3, "size": 3, "rotation": 4}
# No road user is longer, wider or taller (the longest nuScenes boxes, articulated buses and trailers, are
# under 20 m): a larger size is a corrupt row, not an object.
MAX_BOX_SIZE_M = 100.0


def _flat_numbers(values: list[Any], n: int) -> Iterator[float]:
    """Every value as `n` numbers in a row; ValueError at a value that is not `n` numbers."""
    for value in values:
        if type(value) is not list or len(value) != n:
            raise ValueError(n)
        for v in value:
            if type(v) not in (int, float):  # bools and strings too: the row is found and named
                raise ValueError(n)
            yield v


def _numbers(tokens: list[str], values: list[Any], key: str) -> np.ndarray:
    """`(N, 3|4) float64` the rows' `values` of a numeric field, checked: finite; sizes positive and at
    most `MAX_BOX_SIZE_M`; rotations unit quaternions (within 1e-3). `OccDataError` naming the first bad row."""
    n = _WIDTH[key]
    try:
        arr = np.fromiter(_flat_numbers(values, n), np.float64, count=len(values) * n).reshape(-1, n)
    except (ValueError, OverflowError):
        for token, value in zip(tokens, values, strict=True):  # find the row and say what is wrong with it
            _finite_floats(token, value, key, n)
        raise OccDataError(f"sample_annotation.json: a {key} value is not {n} numbers") from None  # (bools only)
    bad = ~np.isfinite(arr).all(axis=1)
    what = "is not finite"
    if key == "size" and not bad.any():
        bad, what = ~(arr > 0).all(axis=1), "is not positive"
    if key == "size" and not bad.any():
        bad, what = (arr > MAX_BOX_SIZE_M).any(axis=1), f"is not a plausible box size (over {MAX_BOX_SIZE_M:g} m)"
    if key == "rotation" and not bad.any():
        with np.errstate(over="ignore", invalid="ignore"):  # a huge value is reported, not warned about
            bad, what = ~(np.abs(np.linalg.norm(arr, axis=1) - 1.0) <= 1e-3), "is not a unit quaternion"
    if bad.any():
        i = int(np.argmax(bad))
        raise OccDataError(f"sample_annotation.json: sample_annotation {tokens[i]!r} {key} {arr[i].tolist()} {what}")
    return arr


def _integers(values: list[Any]) -> Iterator[int]:
    for v in values:
        if type(v) is int or (type(v) is float and v.is_integer()):
            yield int(v)
        else:
            raise ValueError("num_lidar_pts")


def _counts(tokens: list[str], values: list[Any]) -> np.ndarray:
    """`(N,) int64` num_lidar_pts, each a JSON integer (an integral float is accepted)."""
    try:
        return np.fromiter(_integers(values), np.int64, count=len(values))
    except (ValueError, OverflowError):
        for token, value in zip(tokens, values, strict=True):
            try:
                integer(value, f"sample_annotation {token!r} num_lidar_pts")
            except RowProblem as exc:
                raise OccDataError(f"sample_annotation.json: {exc}") from None
        raise OccDataError("sample_annotation.json: a num_lidar_pts value is out of range") from None


def _finite_floats(token: str, raw: Any, key: str, n: int) -> None:
    """Raise `OccDataError` naming the row if its `key` value `raw` is not `n` finite numbers."""
    src = f"sample_annotation {token!r}"
    try:
        if isinstance(raw, list) and any(isinstance(v, (str, bool)) for v in raw):
            raise RowProblem(f"{src} {key} is not numeric ({short(raw)})")
        values = floats(raw, (n,), f"{src} {key}")
    except RowProblem as exc:
        raise OccDataError(f"sample_annotation.json: {exc}") from None
    if not np.isfinite(values).all():
        raise OccDataError(f"sample_annotation.json: {src} {key} {values.tolist()} is not finite")


def _category_name(categories: dict[str, dict[str, Any]], inst_tok: str, inst: dict[str, Any]) -> str:
    category = ref(categories, field(inst, "category_token", "instance"), "category", f"instance {inst_tok!r}")
    name = field(category, "name", "category")
    if not isinstance(name, str) or not name:
        raise OccDataError(f"category.json: row {category['token']!r} has no category name")
    return name


# An instance moves when its box centre's ground-plane (x-y) extent over the scene reaches this many
# metres; the height is left out (annotators' z jitter is no motion). The one definition of
# "moving": the labels generator holds the others at their nearest pose, the fidelity measures score it.
MOVING_TRAVEL_M = 1.0


def moving_instances(boxes_by_keyframe: Sequence[Sequence[BoxRecord]], travel: float = MOVING_TRAVEL_M) -> set[str]:
    """Instance tokens whose box centres span `travel` metres or more in x or y (global frame) over the
    keyframes' boxes `boxes_by_keyframe` (per keyframe, its `BoxRecord`s)."""
    centers: dict[str, list[np.ndarray]] = {}
    for boxes in boxes_by_keyframe:
        for b in boxes:
            centers.setdefault(b.instance_token, []).append(np.asarray(b.center_global, np.float64))
    return {k for k, c in centers.items() if np.ptp(np.stack(c)[:, :2], axis=0).max() >= travel}
