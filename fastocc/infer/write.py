"""`fastocc predict`: a checkpoint's predictions over a split, written in the Occ3D layout.

    OUT/<scene name>/<sample token>/labels.npz     key `semantics`, (200, 200, 16) uint8, 17 = free
    OUT/pictures/<nnn>_<scene>_<token>.png         with --png N: N samples spread over the split

Every file is written to a temporary name in its folder and renamed into place, so a crash never leaves
a truncated file behind (files already written stay valid). `occdata eval --pred OUT` scores the folder.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from fastocc.checkpoint import check_checkpoint_file, load_model
from fastocc.infer.common import check_device, split_indices
from fastocc.infer.predict import PredictConfig, predict_split
from fastocc.model.config import ModelConfig
from fastocc.storegrid import check_store_grid, check_store_rig
from occdata.errors import OccDataError
from occdata.fileio import write_atomic
from occdata.formats.occ3d import label_path, write_label
from occdata.store.reader import StoreReader, open_store
from occdata.view.render import prediction_picture

__all__ = ["PredictRun", "PredictSummary", "picture_indices", "run_predict", "write_predictions"]

PICTURES_DIR = "pictures"


@dataclass(frozen=True)
class PredictRun:
    """`fastocc predict` options. `png`: how many pictures (spread evenly over the split's samples)."""

    checkpoint: Path
    out: Path
    predict: PredictConfig
    png: int = 0
    progress: bool = True
    prefer_ema: bool = True


@dataclass(frozen=True)
class PredictSummary:
    out: Path
    files: int
    pictures: tuple[Path, ...] = field(default_factory=tuple)
    seconds: float = 0.0


def picture_indices(indices: np.ndarray, n: int) -> list[int]:
    """`n` store indices spread evenly over `indices` (all of them when n >= len)."""
    if n <= 0 or not len(indices):
        return []
    pick = np.unique(np.round(np.linspace(0, len(indices) - 1, min(n, len(indices)))).astype(np.int64))
    return [int(indices[k]) for k in pick]


def _scene_name(reader: StoreReader, index: int) -> str:
    return str(reader.attrs["scenes"][int(reader.small("sample/scene_index")[index])]["name"])


def _write_picture(reader: StoreReader, path: Path, index: int, pred: np.ndarray, gt: np.ndarray | None,
                   mask: np.ndarray | None, title: str) -> None:
    images = reader.images(index, reduce=2)
    img = prediction_picture(images, pred, gt, mask, camera_names=reader.attrs.get("camera_order", ()),
                             title=title)
    ok, data = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"cannot encode {path}")
    write_atomic(path, data.tobytes())


def write_predictions(model: nn.Module, model_cfg: ModelConfig, out: Path, cfg: PredictConfig, png: int = 0,
                      progress: bool = True, rank: int | None = None,
                      world_size: int | None = None) -> PredictSummary:
    """Predict the split of `cfg` and write `OUT/<scene>/<token>/labels.npz` (+ `png` pictures).

    `rank`/`world_size` (None: from torch.distributed when initialised): this rank predicts and
    writes its shard only (whole scenes, in order, as `fastocc eval` shards), so the ranks write
    disjoint files; the summary counts this rank's files."""
    t0 = time.perf_counter()
    out = Path(out)
    reader = open_store(cfg.store)
    check_store_grid(reader, model_cfg, "predict")  # its pictures compare with the store's labels
    indices = split_indices(reader, cfg.split)
    if not len(indices):
        raise OccDataError(f"split {cfg.split!r} of {cfg.store} has no built samples")
    if out.exists() and not out.is_dir():
        raise OccDataError(f"--out {out} exists and is not a folder")
    wanted = {idx: k for k, idx in enumerate(picture_indices(indices, png))}
    pictures: list[Path] = []
    files = 0
    sharded = (world_size or 1) > 1 or (world_size is None and torch.distributed.is_available()
                                        and torch.distributed.is_initialized()
                                        and torch.distributed.get_world_size() > 1)
    with tqdm(total=None if sharded else len(indices), desc="predict", unit="sample", disable=not progress,
              dynamic_ncols=True) as bar:
        for batch, probs in predict_split(model, model_cfg, cfg, rank=rank, world_size=world_size):
            pred = probs.argmax(1).to(torch.uint8).numpy()
            del probs
            for b in range(len(batch)):
                idx = int(batch.sample_index[b])
                token, scene = reader.token(idx), _scene_name(reader, idx)
                write_label(label_path(out, scene, token), {"semantics": pred[b]})
                files += 1
                if idx in wanted:
                    has = bool(batch.has_labels[b])
                    gt = batch.semantics[b].numpy().astype(np.uint8) if has else None
                    mask = batch.mask_camera[b].numpy().astype(np.uint8) if has else None
                    path = out / PICTURES_DIR / f"{wanted[idx]:03d}_{scene}_{token}.png"
                    title = f"{scene}  sample {token}  (store index {idx}){'  TTA' if cfg.tta else ''}"
                    _write_picture(reader, path, idx, pred[b], gt, mask, title)
                    pictures.append(path)
            bar.update(len(batch))
    return PredictSummary(out=out, files=files, pictures=tuple(sorted(pictures)), seconds=time.perf_counter() - t0)


def run_predict(run: PredictRun) -> PredictSummary:
    """`fastocc predict`: load the checkpoint (its own model config) and `write_predictions`.

    Under torchrun (WORLD_SIZE > 1) the processes join a process group and each writes its shard of
    the split (whole scenes, so temporal queues are intact): the files are those of one process,
    byte for byte. Every rank returns the combined summary (all files, all pictures)."""
    from fastocc import dist as D

    check_checkpoint_file(run.checkpoint)  # a mistyped checkpoint is said first
    check_device(run.predict.device)
    split_indices(run.predict.store, run.predict.split)  # unknown split / bad store before loading weights
    joined = not (torch.distributed.is_available() and torch.distributed.is_initialized())
    info = D.setup(run.predict.device)
    try:
        # cuda:LOCAL_RANK under torchrun; "auto" as resolved
        chosen = info.enabled or run.predict.device == "auto"
        cfg = replace(run.predict, device=str(info.device)) if chosen else run.predict
        model, ckpt = load_model(run.checkpoint, device=cfg.device, prefer_ema=run.prefer_ema)
        check_store_rig(cfg.store, ckpt.cameras, ckpt.model_config.num_cams, str(run.checkpoint), "predict")
        summary = write_predictions(model, ckpt.model_config, run.out, cfg, png=run.png,
                                    progress=run.progress and info.is_main)
        if not info.enabled:
            return summary
        files = sum(D.gather_ints(summary.files, info))
        pictures: list[object] = [None] * info.world_size
        torch.distributed.all_gather_object(pictures, [str(p) for p in summary.pictures])
        every = tuple(sorted(Path(p) for part in pictures for p in part))  # type: ignore[union-attr]
        return replace(summary, files=files, pictures=every)
    finally:
        if joined:
            D.teardown(info)
