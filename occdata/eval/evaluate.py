"""Score prediction files against a store's labels: `occdata eval` (Occ3D mIoU + RayIoU, and OpenOcc
v2's mAVE + OccScore when the store and the predictions carry flow; no torch).

Predictions are `uint8` label grids `(200, 200, 16)` (x, y, z; 17 = free) in either layout:
- Occ3D: `PRED/<scene>/<token>/labels.npz` with key `semantics`;
- flat: `PRED/<token>.npz` with key `semantics` or `pred`;
optionally with `flow` `(200, 200, 16, 2)` float (vx, vy) m/s. With `pred_classes="openocc-v2"` the
labels are OpenOcc v2 ids (free 16; e.g. `occdata labels --grid openocc-v2` output).
Ground truth, masks, flow and poses come from the store. Samples are streamed one at a time (constant
memory); the table helpers are shared with `fastocc eval`.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np

from occdata.constants import CLASS_NAMES, FREE_LABEL
from occdata.errors import OccDataError
from occdata.eval.flow import MOVING_CLASSES, RayFlowAccumulator
from occdata.eval.metrics import MIoUAccumulator, MIoUResult, RayIoUAccumulator, RayIoUResult
from occdata.eval.rays import store_ray_origins
from occdata.formats.occ3d import LABEL_FILE, label_keys, list_label_files, read_prediction_flow
from occdata.text import plural

__all__ = [
    "EvalConfig",
    "EvalReport",
    "evaluate_predictions",
    "find_predictions",
    "flow_line",
    "format_table",
    "results_dict",
    "summary_line",
]

MaskName = Literal["camera", "lidar", "none"]
T = TypeVar("T")
_MASK_ARRAY = {"camera": "labels/mask_camera", "lidar": "labels/mask_lidar"}


@dataclass(frozen=True)
class EvalConfig:
    """What `occdata eval` scores: prediction folder `pred`, store, split, visibility mask for mIoU."""

    pred: Path
    store: str | Path = "data.zarr"  # a path or an fsspec URL
    split: str = "val"
    mask: MaskName = "camera"
    rayiou: bool = True
    progress: bool = True
    pred_classes: str = "occ3d"  # or "openocc-v2": the prediction files' label ids (occdata.formats.occ3d)


@dataclass(frozen=True)
class EvalReport:
    split: str
    mask: str
    n_samples: int
    n_unlabelled_skipped: int
    miou: MIoUResult
    rayiou: RayIoUResult | None
    seconds: float
    flow_note: str | None = None  # why mAVE / OccScore are not available (None: they are scored)
    grid: str | None = None  # the store's label grid when not Occ3D's (e.g. "surroundocc, all-ones masks")


def find_predictions(pred: Path) -> dict[str, Path]:
    """Token -> prediction file for every `<scene>/<token>/labels.npz` and `<token>.npz` under `pred`."""
    pred = Path(pred)
    if not pred.is_dir():
        raise OccDataError(f"prediction folder not found: {pred}")
    found: dict[str, Path] = {}
    nested = [(p.parent.name, p) for p in list_label_files(pred)]
    for token, path in nested + [(p.stem, p) for p in sorted(pred.glob("*.npz"))]:
        if token in found:
            raise OccDataError(f"two predictions for token {token}: {found[token]} and {path}")
        found[token] = path
    return found


def _split_samples(reader: Any, split: str) -> tuple[list[int], int]:
    """Committed store indices of `split` with labels, and how many committed ones lack labels."""
    in_split = reader.split_indices(split)
    if in_split.size == 0:
        raise OccDataError(f"split '{split}' has no samples in store {reader.path}")
    labelled = reader.split_indices(split, labelled=True)
    if not labelled.size:
        raise OccDataError(f"split '{split}' has no labelled samples in store {reader.path} (nothing to score)")
    return [int(i) for i in labelled], int(in_split.size - labelled.size)


def _iter_label_blocks(reader: Any, indices: list[int],
                       names: tuple[str, ...]) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    """Yield (index, {name: array}) for sorted `indices`, reading each array one storage block (shard)
    at a time: per-sample zarr reads cost more than the metric; memory stays one block."""
    arrays = {name: reader.array(name) for name in names}
    first = arrays[names[0]]
    block = int((first.shards or first.chunks)[0])
    pos = 0
    while pos < len(indices):
        lo = indices[pos] // block * block
        hi = min(lo + block, reader.n_samples)
        try:
            data = {name: np.asarray(a[lo:hi]) for name, a in arrays.items()}
        except Exception as exc:  # noqa: BLE001 - codec errors surface as many types
            raise OccDataError(f"corrupt store data in samples {lo}..{hi - 1} of {reader.path}: {exc}") from None
        while pos < len(indices) and indices[pos] < hi:
            i = indices[pos]
            yield i, {name: d[i - lo] for name, d in data.items()}
            pos += 1


def _read_ahead(items: Iterator[T], depth: int = 4) -> Iterator[T]:
    """Iterate `items` in a background thread, at most `depth` ahead: file and store decoding (zlib,
    zstd release the GIL) overlaps the metric. Exceptions reach the consumer unchanged."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def put(item: tuple[bool, Any]) -> None:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def work() -> None:
        try:
            for x in items:
                put((True, x))
                if stop.is_set():
                    return
            put((True, end))
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer as is
            put((False, exc))

    thread = threading.Thread(target=work, name="occdata-eval-read", daemon=True)
    thread.start()
    try:
        while True:
            ok, x = q.get()
            if not ok:
                raise x
            if x is end:
                return
            yield x
    finally:
        stop.set()


def evaluate_predictions(cfg: EvalConfig) -> EvalReport:
    """Score the prediction files of `cfg.pred` on the labelled samples of `cfg.split`."""
    from tqdm import tqdm

    from occdata.store.reader import open_store

    if cfg.mask not in ("camera", "lidar", "none"):
        raise OccDataError(f"unknown mask '{cfg.mask}' (camera, lidar or none)")
    reader = open_store(cfg.store)
    indices, n_unlabelled = _split_samples(reader, cfg.split)
    files = find_predictions(cfg.pred)
    if not files:
        raise OccDataError(f"no predictions in {cfg.pred} (expected <scene>/<token>/labels.npz or <token>.npz)")
    store_tokens = [reader.token(i) for i in range(reader.n_samples)]
    index_of = {t: i for i, t in enumerate(store_tokens)}
    scenes = reader.attrs["scenes"]
    scene_index = reader.small("sample/scene_index")
    unknown = sorted(t for t in files if t not in index_of)
    if unknown:
        raise OccDataError(f"{len(unknown)} prediction(s) for tokens not in store {reader.path}, "
                           f"e.g. {files[unknown[0]]}")
    for token, path in files.items():
        if path.name == LABEL_FILE:
            want = scenes[int(scene_index[index_of[token]])]["name"]
            if path.parent.parent.name != want:
                raise OccDataError(f"{path}: sample {token} belongs to scene {want}, not {path.parent.parent.name}")
    missing = [i for i in indices if store_tokens[i] not in files]
    if missing:
        i = missing[0]
        scene = scenes[int(scene_index[i])]["name"]
        raise OccDataError(f"{len(missing)} of {len(indices)} labelled '{cfg.split}' samples have no prediction, "
                           f"e.g. {store_tokens[i]} (expected {cfg.pred}/{scene}/{store_tokens[i]}/labels.npz "
                           f"or {cfg.pred}/{store_tokens[i]}.npz)")

    flow_note = _flow_note(reader, cfg, [files[store_tokens[i]] for i in indices])
    with_flow = flow_note is None
    miou = MIoUAccumulator()
    grid = reader.grid.grid  # the store's label grid: Occ3D's, or the one it was built on (--grid)
    ray = ((RayFlowAccumulator if with_flow else RayIoUAccumulator)(grid=grid)) if cfg.rayiou else None
    names = ("labels/semantics",) + ((_MASK_ARRAY[cfg.mask],) if cfg.mask != "none" else ())
    t0 = time.perf_counter()
    bar = tqdm(total=len(indices), desc=f"eval {cfg.split}", unit="sample", disable=not cfg.progress)
    flow_arr = reader.array("labels/flow") if with_flow else None  # per sample: a block of flow is 164 MB

    def with_flow_row(i: int, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return arrays if flow_arr is None else arrays | {"labels/flow": np.asarray(flow_arr[i])}

    samples = ((i, with_flow_row(i, arrays), _prediction(reader, files[store_tokens[i]], cfg.pred_classes))
               for i, arrays in _iter_label_blocks(reader, indices, names))
    for i, arrays, (pred, pred_flow) in _read_ahead(samples):
        path = files[store_tokens[i]]
        gt = arrays["labels/semantics"]
        try:
            miou.update(gt, pred, arrays.get(_MASK_ARRAY.get(cfg.mask, "")))
            if isinstance(ray, RayFlowAccumulator):
                ray.update(gt, pred, store_ray_origins(reader, i), arrays["labels/flow"], pred_flow)
            elif ray is not None:
                ray.update(gt, pred, store_ray_origins(reader, i))
        except OccDataError as exc:
            raise OccDataError(f"{path}: {exc}") from None
        bar.update()
    bar.close()
    return EvalReport(split=cfg.split, mask=cfg.mask, n_samples=len(indices), n_unlabelled_skipped=n_unlabelled,
                      miou=miou.result(), rayiou=ray.result() if ray else None,
                      seconds=time.perf_counter() - t0, flow_note=flow_note, grid=_grid_words(reader))


def _grid_words(reader: Any) -> str | None:
    g = reader.grid
    if "name" not in reader.attrs.get("grid", {}):
        return None  # Occ3D's grid, as every store before grids
    frame = "key ego" if g.frame == "key_ego" else "LIDAR_TOP frame"
    return (f"{g.name} ({'x'.join(map(str, g.shape))}, {g.grid.voxel_size:g} m, {frame}"
            + ("" if g.masks else "; no masks in the source: the store's masks are all ones") + ")")


def _prediction(reader: Any, path: Path, classes: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A prediction on the store's grid; another shape is one line that names the store's grid."""
    try:
        return read_prediction_flow(path, classes, reader.grid.shape)
    except OccDataError as exc:
        if reader.grid.name == "occ3d" or "has shape" not in str(exc):
            raise
        raise OccDataError(f"{exc}: the store's labels are on grid {reader.grid.name} "
                           f"({'x'.join(map(str, reader.grid.shape))}, {reader.grid.grid.voxel_size:g} m)") from None


def _flow_note(reader: Any, cfg: EvalConfig, paths: list[Path]) -> str | None:
    """None when mAVE is scored (the store has flow and every prediction carries it), else why not.
    Predictions that mix files with and without flow are one error (scored with flow for all or none);
    only each file's zip directory is read here."""
    if not cfg.rayiou:
        return "mAVE is scored on RayIoU's rays (--no-rayiou)"
    has = [("flow" in (label_keys(p) or ())) for p in paths]
    with_flow = [p for p, h in zip(paths, has, strict=True) if h]
    if with_flow and len(with_flow) < len(paths):
        without = paths[has.index(False)]
        raise OccDataError(f"{len(with_flow)} of {len(paths)} predictions carry 'flow' (e.g. {with_flow[0]}) and "
                           f"the others do not (e.g. {without}): give every prediction a flow, or none")
    if not reader.has_flow:
        return "the store has no flow (build it with --gts from OpenOcc v2 labels)"
    if not with_flow:
        return "the predictions carry no 'flow' array"
    return None


def _pct(x: float) -> float | None:
    return None if math.isnan(x) else round(100.0 * float(x), 4)


def results_dict(miou: MIoUResult, rayiou: RayIoUResult | None, **extra: Any) -> dict[str, Any]:
    """JSON-ready summary, values in PERCENT (null where a class is absent: 0/0)."""
    out: dict[str, Any] = {"unit": "percent", **extra, "miou": _pct(miou.miou), "geo_iou": _pct(miou.geo_iou)}
    flow = rayiou is not None and rayiou.ave_per_class is not None
    if rayiou is not None:
        out["rayiou"] = _pct(rayiou.rayiou)
        out["rayiou_at"] = {f"{t:g}": _pct(v) for t, v in rayiou.rayiou_at.items()}
    if flow:
        out["mave"] = None if math.isnan(rayiou.mave) else round(float(rayiou.mave), 6)
        out["mave_unit"] = "m/s"
        out["occ_score"] = _pct(rayiou.occ_score)
    per = {}
    for c, name in enumerate(CLASS_NAMES[:FREE_LABEL]):
        row: dict[str, float | None] = {"iou": _pct(miou.per_class_iou[c])}
        if rayiou is not None:
            for j, t in enumerate(rayiou.rayiou_at):
                row[f"rayiou@{t:g}"] = _pct(rayiou.per_class[j, c])
        if flow and c in MOVING_CLASSES:
            ave = rayiou.ave_per_class[c]
            row["ave"] = None if math.isnan(ave) else round(float(ave), 6)  # m/s
        per[name] = row
    out["per_class"] = per
    return out


def format_table(miou: MIoUResult, rayiou: RayIoUResult | None) -> str:
    """Per-class table (percent; '-' where a class is absent from truth and prediction)."""

    def f(x: float) -> str:
        return f"{100 * x:8.2f}" if not math.isnan(x) else f"{'-':>8}"

    def mps(x: float) -> str:
        return f"{x:11.3f}" if not math.isnan(x) else f"{'-':>11}"

    taus = list(rayiou.rayiou_at) if rayiou is not None else []
    ave = rayiou.ave_per_class if rayiou is not None else None
    head = f"{'class':22s}{'IoU':>8}" + "".join(f"{'RayIoU@' + format(t, 'g'):>11}" for t in taus)
    head += f"{'AVE m/s':>11}" if ave is not None else ""
    lines = [head, "-" * len(head)]
    for c, name in enumerate(CLASS_NAMES[:FREE_LABEL]):
        row = f"{name:22s}{f(miou.per_class_iou[c])}"
        if rayiou is not None:
            row += "".join(f"   {f(rayiou.per_class[j, c])}" for j in range(len(taus)))
        if ave is not None:
            row += mps(ave[c]) if c in MOVING_CLASSES else f"{'':11}"
        lines.append(row)
    lines.append("-" * len(head))
    mean = f"{'mean':22s}{f(miou.miou)}"
    if rayiou is not None:
        mean += "".join(f"   {f(v)}" for v in rayiou.rayiou_at.values())
    if ave is not None and rayiou is not None:
        mean += mps(rayiou.mave)
    lines.append(mean)
    return "\n".join(lines)


def summary_line(report: EvalReport) -> str:
    on = "" if report.grid is None else f" on grid {report.grid}"
    s = (f"{report.split}{on}: {plural(report.n_samples, 'sample')}, mIoU {100 * report.miou.miou:.2f} "
         f"(mask {report.mask}), geometry IoU {100 * report.miou.geo_iou:.2f}")
    if report.rayiou is not None:
        at = ", ".join(f"@{t:g} {100 * v:.2f}" for t, v in report.rayiou.rayiou_at.items())
        s += f", RayIoU {100 * report.rayiou.rayiou:.2f} ({at})"
        if report.rayiou.ave_per_class is not None:
            s += (f", mAVE {report.rayiou.mave:.3f} m/s, OccScore {100 * report.rayiou.occ_score:.2f}"
                  if not math.isnan(report.rayiou.mave) else
                  ", mAVE n/a (no true-positive ray of a moving class), OccScore n/a")
    return s + f"; {report.n_samples / max(report.seconds, 1e-9):.1f} samples/s"


def flow_line(report: EvalReport) -> str | None:
    """The one line that says mAVE / OccScore are not available and why (None: scored, or not asked)."""
    return None if report.flow_note is None else f"mAVE, OccScore: not available ({report.flow_note})"
