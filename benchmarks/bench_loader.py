"""Benchmark the training loader: samples/s per worker process, ours vs a peer-style loader.

Ours: `StoreDataset` (train augmentation, depth targets, BEV aug, temporal poses), one process.
Reference, written to do what peer loaders do per sample: read and fully decode the 6 JPEG files,
resize / crop / flip / rotate as separate image ops, normalise in numpy, load the raw LiDAR sweep and
project it into every camera (matrix chain per camera), rasterise the depth map in numpy, load the
label npz and flip it. Both run on the same samples in the same run.

    taskset -c 0 python -m benchmarks.bench_loader [--samples 40] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import SHARED_DATA, write_json
from benchmarks.provenance import machine
from fastocc.data import BevAugConfig, ImageAugConfig, LoaderConfig, SampleConfig, StoreDataset
from fastocc.data.augment import sample_image_aug
from occdata.sensors.image_ops import IMAGENET_MEAN, IMAGENET_STD
from occdata.store.build import BuildConfig, build_store
from occdata.store.layout import token_str
from occdata.store.reader import open_store

__all__ = ["PeerLoader", "bench_ours", "bench_peer", "make_half_scale_store", "make_store"]


def make_store(tmp: Path, n_scenes: int, n_samples: int) -> tuple[Path, Path]:
    from tests.replicated_tree import make_replicated_tree

    label = next((SHARED_DATA / "occ3d-label").glob("*/labels.npz"))
    tree = make_replicated_tree(SHARED_DATA / "nuscenes-real", label, tmp / "ns", n_scenes, n_samples)
    store = tmp / "s.zarr"
    build_store(BuildConfig(root=tree, out=store, gts=tree / "gts", block_samples=8, progress=False))
    return tree, store


def make_half_scale_store(tree: Path, tmp: Path) -> Path:
    """The same samples with images re-encoded at 0.5 scale (`occdata build --image-scale 0.5`)."""
    from occdata.store.sample import SampleOptions

    store = tmp / "s_half.zarr"
    build_store(BuildConfig(root=tree, out=store, gts=tree / "gts", block_samples=8, progress=False,
                            options=SampleOptions(image_scale=0.5)))
    return store


class PeerLoader:
    """Per-sample work of a typical BEVDet/BEVDepth-style pipeline (no store)."""

    def __init__(self, tree: Path, store: Path, height: int, width: int) -> None:
        self.tree, self.h, self.w = tree, height, width
        sd = json.loads((tree / "v1.0-mini" / "sample_data.json").read_text())
        self.file_of = {r["token"]: r["filename"] for r in sd}
        r = open_store(store)
        self.cam_tokens = r.small("cam/token")
        self.lidar_tokens = r.small("sample/lidar_token")
        self.sample_tokens = r.small("sample/token")
        self.scene = [r.attrs["scenes"][k]["name"] for k in r.small("sample/scene_index")]
        self.K = r.small("calib/K")
        self.T_ego_from_cam = r.small("calib/T_ego_from_cam")
        self.T_ego_from_lidar = r.small("calib/T_ego_from_lidar")
        self.T_global_from_keyego = r.small("pose/T_global_from_keyego")
        self.T_global_from_ego_cam = r.small("pose/T_global_from_ego_cam")
        self.cfg = ImageAugConfig(height=height, width=width)

    def __call__(self, i: int, rng: np.random.Generator) -> dict:
        pts = np.fromfile(self.tree / self.file_of[token_str(self.lidar_tokens[i])], dtype=np.float32)
        pts = pts.reshape(-1, 5)[:, :3].T
        imgs, depths = [], []
        for c in range(6):
            img = cv2.imread(str(self.tree / self.file_of[token_str(self.cam_tokens[i, c])]))  # full decode
            aug = sample_image_aug(self.cfg, img.shape[1], img.shape[0], rng)
            new = (int(img.shape[1] * aug.scale), int(img.shape[0] * aug.scale))
            img = cv2.resize(img, new, interpolation=cv2.INTER_LINEAR)
            x0, y0 = int(aug.crop_x), int(aug.crop_y)
            img = img[y0: y0 + self.h, x0: x0 + self.w]
            if aug.flip:
                img = img[:, ::-1]
            R = cv2.getRotationMatrix2D(((self.w - 1) / 2, (self.h - 1) / 2), -aug.rot_deg, 1.0)
            img = cv2.warpAffine(np.ascontiguousarray(img), R, (self.w, self.h))
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32)
            imgs.append(((img - np.float32(IMAGENET_MEAN)) / np.float32(IMAGENET_STD)).transpose(2, 0, 1))
            # Raw LiDAR -> camera, per camera and sample (devkit chain).
            T = (np.linalg.inv(self.T_ego_from_cam[i, c]) @ np.linalg.inv(self.T_global_from_ego_cam[i, c])
                 @ self.T_global_from_keyego[i] @ self.T_ego_from_lidar[i]).astype(np.float32)
            p = T[:3, :3] @ pts + T[:3, 3:4]
            uv = (self.K[i, c].astype(np.float32) @ p)[:2] / p[2]
            keep = (p[2] > 1.0) & (uv[0] > 1) & (uv[0] < 1599) & (uv[1] > 1) & (uv[1] < 899)
            uv1 = np.vstack([uv[:, keep], np.ones(keep.sum(), np.float32)])
            q = (aug.matrix @ uv1)[:2]
            d = p[2, keep]
            col, row = np.round(q[0]).astype(int), np.round(q[1]).astype(int)
            ok = (col >= 0) & (col < self.w) & (row >= 0) & (row < self.h) & (d < 45.0)
            col, row, d = col[ok], row[ok], d[ok]
            order = np.lexsort((d, row * self.w + col))  # nearest first per pixel (BEVDepth-style)
            key = (row * self.w + col)[order]
            first = np.r_[True, key[1:] != key[:-1]]
            dm = np.zeros((self.h, self.w), np.float32)
            dm[row[order][first], col[order][first]] = d[order][first]
            depths.append(np.where(dm > 0, dm, np.inf).reshape(self.h // 16, 16, self.w // 16, 16).min((1, 3)))
        lab = np.load(self.tree / "gts" / self.scene[i] / token_str(self.sample_tokens[i]) / "labels.npz")
        sem = lab["semantics"]
        if rng.random() < 0.5:
            sem = sem[::-1]
        return {"images": np.stack(imgs), "depth": np.stack(depths), "semantics": np.ascontiguousarray(sem)}


def bench_ours(store: Path, height: int, width: int, n: int) -> float:
    sample = SampleConfig(image=ImageAugConfig(height=height, width=width), bev=BevAugConfig())
    ds = StoreDataset(LoaderConfig(store=store, batch_size=1, sample=sample, seed=1))
    it = iter(ds)
    next(it)  # warm-up: numba kernels, store handles
    t0 = time.perf_counter()
    k = 0
    for _ in it:
        k += 1
        if k == n:
            break
    return k / (time.perf_counter() - t0)


def bench_peer(tree: Path, store: Path, height: int, width: int, n: int) -> float:
    peer = PeerLoader(tree, store, height, width)
    idx = open_store(store).done_indices()
    peer(int(idx[0]), np.random.default_rng(0))
    t0 = time.perf_counter()
    for k in range(n):
        peer(int(idx[(k + 1) % len(idx)]), np.random.default_rng(k))
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=40, help="timed samples per loader and size")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    record = machine()
    with tempfile.TemporaryDirectory() as d:
        tree, store = make_store(Path(d), 2, (args.samples + 2) // 2 + 1)
        half = make_half_scale_store(tree, Path(d))
        result: dict = {"machine": record, "samples": args.samples, "sizes": {}}
        for h, w in ((256, 704), (320, 800)):
            ours = bench_ours(store, h, w, args.samples)
            ours_half = bench_ours(half, h, w, args.samples)
            peer = bench_peer(tree, store, h, w, args.samples)
            result["sizes"][f"{h}x{w}"] = {
                "ours_samples_per_s": round(ours, 1), "ours_half_scale_store_samples_per_s": round(ours_half, 1),
                "peer_samples_per_s": round(peer, 1), "ratio": round(ours / peer, 2),
                "ratio_half_scale_store": round(ours_half / peer, 2),
            }
            print(f"{h}x{w}: ours {ours:.1f} samples/s (store at --image-scale 0.5: {ours_half:.1f}), "
                  f"peer-style {peer:.1f} samples/s, ratio {ours / peer:.2f}x / {ours_half / peer:.2f}x", flush=True)
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        result["max_rss_mb"] = round(rss_mb)
        print(f"peak RSS of this (single worker) process: {rss_mb:.0f} MB")
    if args.json:
        write_json(result, args.json)


if __name__ == "__main__":
    main()
