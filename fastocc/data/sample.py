"""Read samples from a store in chunk-aligned runs and turn them into per-sample training arrays."""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field

import cv2
import numpy as np

from fastocc.data.augment import (
    BevAugConfig,
    ImageAugConfig,
    T_decoded_from_original,
    apply_bev_aug,
    choose_reduce,
    sample_bev_aug,
    sample_image_aug,
)
from fastocc.data.batch import IGNORE_LABEL
from fastocc.data.shared import SharedArray, from_shared, to_shared
from occdata.constants import GRID, NUM_CLASSES
from occdata.errors import OccDataError
from occdata.sensors.depth_targets import DEPTH_MAX, DEPTH_MIN, depth_target
from occdata.sensors.image_ops import normalise_chw, normalise_lut
from occdata.store.bev import unpack_bev
from occdata.store.layout import STATE_DONE, STATE_PENDING
from occdata.store.reader import StoreReader, open_store

__all__ = [
    "RawSample",
    "SampleConfig",
    "SampleMaker",
    "StoreSamples",
    "decode_augmented",
    "decode_jpeg",
    "warp_input",
    "warp_normalise",
]

_REDUCE_FLAG = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                8: cv2.IMREAD_REDUCED_COLOR_8}
# The small arrays the loader holds (state, flags, calibration, poses, history, sizes, ids, offsets, checksums).
_SMALL = ("status/state", "labels/present", "status/checksum", "calib/K", "calib/T_keyego_from_cam",
          "pose/T_global_from_keyego", "temporal/prev_index", "temporal/prev_valid", "cam/image_size",
          "sample/scene_index", "sample/split", "images/offsets", "depth/offsets")
_LABELS = ("labels/semantics", "labels/mask_camera", "labels/mask_lidar", "labels/bev")


@dataclass(frozen=True)
class SampleConfig:
    image: ImageAugConfig = field(default_factory=ImageAugConfig)
    bev: BevAugConfig = field(default_factory=BevAugConfig)
    depth_stride: int = 16
    depth_range: tuple[float, float] = (DEPTH_MIN, DEPTH_MAX)


@dataclass
class RawSample:
    """Undecoded payload of one sample: JPEG streams, LiDAR (u, v, d) per camera (the store's C
    cameras, in its `camera_order`), labels or None."""

    index: int
    jpegs: list[np.ndarray]  # C x (bytes,) uint8
    uvd: list[np.ndarray]  # C x (M_c, 3) float32, pixels of camera c's original image
    labels: dict[str, np.ndarray] | None  # _LABELS -> per-sample arrays


class StoreSamples:
    """Store access for the loader: small arrays read once per process tree, big ones per contiguous run.

    Pickled (a forkserver or spawn loader worker), the small arrays travel in shared memory
    (`fastocc.data.shared`) and the worker's reader opens the store's metadata only (one request with
    consolidated metadata), never re-reading them. Forked, the worker inherits them (`for_this_process`).
    """

    def __init__(self, reader: StoreReader) -> None:
        self.reader = reader
        self._pid = os.getpid()
        self._shared: dict[str, SharedArray] | None = None
        r = reader
        r.small_many(_SMALL)  # one round trip for the packed copies
        self.n_cams = r.n_cams  # C: the store's cameras (attrs camera_order), each with its own image size
        self.state = r.small("status/state")
        self.present = r.small("labels/present")
        r.small("status/checksum")  # what check_rows compares with: read here, shared with the workers
        self.K = r.small("calib/K").astype(np.float32)
        self.T_keyego_from_cam = r.small("calib/T_keyego_from_cam").astype(np.float32)
        self.T_global_from_keyego = r.small("pose/T_global_from_keyego")  # float64: relative poses need it
        self.prev_index = r.small("temporal/prev_index").astype(np.int64)
        self.prev_valid = r.small("temporal/prev_valid")
        self.image_size = r.small("cam/image_size")  # (S, C, 2) int32 (width, height) of each original image
        self.scene_index = r.small("sample/scene_index")
        self.split = r.small("sample/split")
        self.img_off = r.small("images/offsets")
        self.uvd_off = r.small("depth/offsets")
        self.stored_scale = float(r.attrs.get("images", {}).get("scale", 1.0))
        self.block = int(r.array("status/state").chunks[0])

    def _arrays(self) -> dict[str, np.ndarray]:
        """Every array this object holds: its own (`.name`) and the reader's cache (`reader:name`)."""
        own = {k: v for k, v in self.__dict__.items() if isinstance(v, np.ndarray)}
        return own | {f"reader:{k}": v for k, v in self.reader._cache.items()}

    def __getstate__(self) -> dict:
        if self._shared is None:  # copied into shared memory once; later pickles pass descriptors only
            self._shared = {k: to_shared(v) for k, v in self._arrays().items()}
            self._use_shared()  # this process too: the private copies are freed, one copy in all
        plain = {k: v for k, v in self.__dict__.items()
                 if k not in ("reader", "_shared") and not isinstance(v, np.ndarray)}
        return {"plain": plain, "shared": self._shared, "store": self.reader.path}

    def _use_shared(self) -> None:
        for k, v in (self._shared or {}).items():
            if k.startswith("reader:"):
                self.reader._cache[k.removeprefix("reader:")] = from_shared(v)
            else:
                setattr(self, k, from_shared(v))

    def __setstate__(self, state: dict) -> None:
        arrays = {k: from_shared(v) for k, v in state["shared"].items()}
        self.__dict__.update(state["plain"])
        self.__dict__.update({k: v for k, v in arrays.items() if not k.startswith("reader:")})
        self._shared, self._pid = state["shared"], os.getpid()
        self.reader = open_store(state["store"], check_metadata=False, packed=True)  # the parent checked it
        self.reader.preload({k.removeprefix("reader:"): v for k, v in arrays.items() if k.startswith("reader:")})

    def for_this_process(self) -> StoreSamples:
        """Self, or in a forked child a copy with its own store handle and the inherited arrays."""
        if self._pid == os.getpid():
            return self
        child = copy.copy(self)
        child._pid = os.getpid()
        child.reader = open_store(self.reader.path, check_metadata=False, packed=True)
        child.reader.preload(dict(self.reader._cache))
        return child

    def read_run(self, lo: int, hi: int, wanted: set[int] | None = None) -> list[RawSample]:
        """Samples `lo <= i < hi` (only `wanted` ones if given) with one read per array.

        A read error is traced to the sample it belongs to and raised as OccDataError naming it.
        """
        idx = [i for i in range(lo, hi) if wanted is None or i in wanted]
        if not idx:
            return []
        try:
            return self._read(lo, hi, idx)
        except OccDataError:
            raise
        except Exception as exc:  # noqa: BLE001 - codec / IO errors surface as many types
            for i in idx:  # find the culprit with per-sample reads (they raise OccDataError naming it)
                self._read(i, i + 1, [i], per_sample_errors=True)
            raise OccDataError(f"corrupt store data for samples {lo}..{hi - 1}: {exc}") from None

    def _read(self, lo: int, hi: int, idx: list[int], per_sample_errors: bool = False) -> list[RawSample]:
        g = self.reader.group

        def read(name: str, start: int, stop: int) -> np.ndarray:
            try:
                return np.asarray(g[name][start:stop])
            except Exception as exc:  # noqa: BLE001
                if per_sample_errors:
                    raise OccDataError(
                        f"corrupt store data in {name} for sample {lo} ({self.reader.token(lo)}): {exc}"
                    ) from None
                raise

        def span(off: np.ndarray) -> tuple[int, int]:
            sel = off[[i - lo for i in idx]]
            return int(sel[..., 0].min()), int((sel[..., 0] + sel[..., 1]).max())

        (j0, j1), (u0, u1) = span(self.img_off[lo:hi]), span(self.uvd_off[lo:hi])
        ranges = [("images/jpeg", j0, j1), ("depth/uvd", u0, u1)]
        labelled = [i for i in idx if self.present[i]]
        if labelled:
            ranges += [(name, min(labelled), max(labelled) + 1) for name in _LABELS]
        if per_sample_errors:  # one array at a time: the error names the array
            parts = [read(name, start, stop) for name, start, stop in ranges]
        else:  # all at once: one round trip over an object store
            parts = self.reader.read_ranges(ranges)
        jpeg, uvd = parts[0], parts[1]
        labels = dict(zip(_LABELS, parts[2:], strict=True)) if labelled else {}
        out = []
        check = self.reader.integrity.check_rows  # a missing chunk reads as fill: compare with the checksums
        for i in idx:
            jo, uo = self.img_off[i], self.uvd_off[i]
            lab = {k: v[i - min(labelled)] for k, v in labels.items()} if self.present[i] else None
            raw = RawSample(
                index=i,
                jpegs=[jpeg[int(s) - j0: int(s) - j0 + int(n)] for s, n in jo],
                uvd=[uvd[int(s) - u0: int(s) - u0 + int(n)] for s, n in uo],
                labels=lab,
            )
            if self.state[i] != STATE_PENDING:
                check("images/jpeg", [i], [b"".join(a.tobytes() for a in raw.jpegs)])
                check("depth/uvd", [i], [b"".join(a.tobytes() for a in raw.uvd)])
                for name, row in (lab or {}).items():
                    check(name, [i], [row])
            out.append(raw)
        return out

    def loadable(self, i: int) -> bool:
        return bool(self.state[i] == STATE_DONE)


def decode_jpeg(jpeg: np.ndarray, reduce: int = 1) -> np.ndarray | None:
    """JPEG bytes -> BGR `(h, w, 3) uint8` decoded at 1/`reduce` straight from the DCT, or None if unreadable."""
    return cv2.imdecode(jpeg, _REDUCE_FLAG[reduce])


def warp_input(img: np.ndarray, A: np.ndarray, orig_w: int, orig_h: int, width: int, height: int,
               bgr: bool = True) -> np.ndarray:
    """A camera image at any scale of its original `orig_w x orig_h` -> augmented RGB input
    `(height, width, 3) uint8`: ONE warpAffine with A @ inv(T_decoded_from_original), so a decode
    scale is folded into the warp, not into A. `img` is BGR (OpenCV's decode) unless `bgr` is False."""
    dh, dw = img.shape[:2]
    warp = A @ np.linalg.inv(T_decoded_from_original(orig_w, orig_h, dw, dh))
    out = cv2.warpAffine(img, warp[:2], (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return cv2.cvtColor(out, cv2.COLOR_BGR2RGB) if bgr else out


def warp_normalise(img: np.ndarray, A: np.ndarray, orig_w: int, orig_h: int, lut: np.ndarray, out: np.ndarray,
                   bgr: bool = True) -> None:
    """The network's image preprocessing, shared by the loader and `fastocc.Predictor`: warp with the
    augmentation A (`warp_input`), then normalise into `out (3, H, W) float32` (in place) with
    `lut = normalise_lut()` (ImageNet mean/std, RGB)."""
    normalise_chw(warp_input(img, A, orig_w, orig_h, out.shape[2], out.shape[1], bgr), lut, out)


def decode_augmented(jpeg: np.ndarray, A: np.ndarray, scale: float, orig_w: int, orig_h: int, width: int,
                     height: int, stored_scale: float = 1.0, max_upsample: float = 1.1) -> np.ndarray | None:
    """JPEG bytes -> augmented RGB input `(height, width, 3) uint8`, or None if the JPEG is unreadable.

    Decodes at 1/r straight from the DCT where that is cheap (`choose_reduce`), then `warp_input`.
    """
    img = decode_jpeg(jpeg, choose_reduce(scale, stored_scale, max_upsample))
    if img is None:
        return None
    return warp_input(img, A, orig_w, orig_h, width, height)


class SampleMaker:
    """RawSample -> per-sample dict of numpy arrays keyed like `Batch` fields (see batch.py)."""

    def __init__(self, samples: StoreSamples, cfg: SampleConfig) -> None:
        self.s = samples
        self.cfg = cfg
        self.lut = normalise_lut()

    def __call__(self, raw: RawSample, rng: np.random.Generator | None, seq_start: bool = True) -> dict:
        cfg, s, i = self.cfg, self.s, raw.index
        H, W = cfg.image.height, cfg.image.width
        if H % cfg.depth_stride or W % cfg.depth_stride:
            raise ValueError(f"input size {H}x{W} must be a multiple of the depth stride {cfg.depth_stride}")
        C = s.n_cams
        images = np.empty((C, 3, H, W), dtype=np.float32)
        img_aug = np.empty((C, 3, 3), dtype=np.float64)
        depth = np.empty((C, H // cfg.depth_stride, W // cfg.depth_stride), dtype=np.float32)
        for c in range(C):
            # Each camera is resized/cropped to the input from its own original size: A and the depth
            # targets (LiDAR pixels of that original image moved by A) agree per camera.
            ow, oh = (int(x) for x in s.image_size[i, c])
            aug = sample_image_aug(cfg.image, ow, oh, rng)
            A = aug.matrix
            img = decode_jpeg(raw.jpegs[c], choose_reduce(aug.scale, s.stored_scale, cfg.image.max_upsample))
            if img is None:
                raise OccDataError(f"corrupt image data for sample {i} ({s.reader.token(i)}), camera {c}")
            warp_normalise(img, A, ow, oh, self.lut, images[c])
            img_aug[c] = A
            depth[c] = depth_target(raw.uvd[c], A, H, W, cfg.depth_stride, *cfg.depth_range)
        bev = sample_bev_aug(cfg.bev, rng)
        if raw.labels is not None:
            lab = raw.labels
            semantics = apply_bev_aug(lab["labels/semantics"], bev, IGNORE_LABEL)
            mask_camera = apply_bev_aug(lab["labels/mask_camera"], bev, 0)
            mask_lidar = apply_bev_aug(lab["labels/mask_lidar"], bev, 0)
            bev_target = apply_bev_aug(unpack_bev(lab["labels/bev"], NUM_CLASSES), bev, 0, xy_axes=(1, 2))
        else:
            semantics = np.full(GRID.shape, IGNORE_LABEL, dtype=np.uint8)
            mask_camera = np.zeros(GRID.shape, dtype=np.uint8)
            mask_lidar = mask_camera
            bev_target = np.zeros((NUM_CLASSES, *GRID.shape[:2]), dtype=np.uint8)
        prev = s.prev_index[i]
        # A previous frame that failed to build cannot be loaded: treat it as padding.
        prev_valid = s.prev_valid[i] & (s.state[prev] == STATE_DONE)
        T_cur = s.T_global_from_keyego[i]
        T_cur_from_prev = np.linalg.inv(T_cur)[None] @ s.T_global_from_keyego[prev]
        return {
            "images": images, "K": s.K[i], "T_keyego_from_cam": s.T_keyego_from_cam[i], "img_aug": img_aug,
            "bev_aug": bev.matrix, "T_global_from_keyego": T_cur, "seq_start": seq_start,
            "semantics": semantics, "mask_camera": mask_camera, "mask_lidar": mask_lidar,
            "bev_target": bev_target, "depth_target": depth, "has_labels": raw.labels is not None,
            "sample_index": i, "prev_index": prev, "prev_valid": prev_valid, "T_cur_from_prev": T_cur_from_prev,
        }
