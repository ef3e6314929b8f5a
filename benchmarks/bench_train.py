"""Does `fastocc train` learn? Image-free baseline, checkpoint evaluation and the learning-curve PNG.

    # 1. the best image-free baseline: per-voxel most frequent TRAINING label, scored on val (camera mask)
    python -m benchmarks.bench_train baseline --store data.zarr --json baseline.json
    # 2. val mIoU of every checkpoint of runs (snap_*.pt, epoch_*.pt, last.pt), with the shared evaluation;
    #    a run trained with noise_images = true is scored with noise images too; PNG of loss and mIoU
    python -m benchmarks.bench_train curve --store data.zarr --run runs/img --run runs/noise \\
        --baseline baseline.json --png docs/img/train_curve.png --json curve.json

The metric code is the project's (`occdata.eval.metrics`, `fastocc.infer.score`); nothing is re-implemented.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks.common import write_json
from benchmarks.curves import run_curve
from benchmarks.provenance import machine
from occdata.store.reader import open_store

__all__ = ["baseline", "plot"]


def baseline(store: str, train_split: str = "train", val_split: str = "val") -> dict:
    """Per-voxel most frequent training label (ties: the lower label), scored on the val split
    (`occdata.eval.baseline`, also `occdata baseline`)."""
    from occdata.eval.baseline import image_free_baseline

    r = image_free_baseline(open_store(store), train_split, val_split)
    return {"store": str(store), "train_samples": r.train_samples, "val_samples": r.samples,
            "miou_camera_mask": r.miou_camera_mask, "miou_no_mask": r.miou_no_mask,
            "per_class_iou_camera_mask": [None if np.isnan(x) else x for x in r.per_class_iou_camera_mask]}


def plot(curves: list[dict], baseline_miou: float | None, path: Path) -> None:
    """Loss (left) and val mIoU (right) against samples seen; drawn with OpenCV (no plotting dependency)."""
    W, H, pad = 1200, 480, 60
    img = np.full((H, W, 3), 255, np.uint8)
    colours = [(200, 80, 0), (0, 0, 200), (0, 150, 0), (150, 0, 150)]
    panels = [(pad, pad, W // 2 - pad, H - pad), (W // 2 + pad, pad, W - pad, H - pad)]
    xs = [x for c in curves for x, _ in c["loss"]] + [p["samples_seen"] for c in curves for p in c["points"]]
    xmax = max(xs) if xs else 1
    losses = [v for c in curves for _, v in c["loss"]]
    lmin, lmax = (min(losses), max(losses)) if losses else (0, 1)
    mious = [100 * p["miou"] for c in curves for p in c["points"]] + ([100 * baseline_miou] if baseline_miou else [])
    mmax = max(mious + [1.0]) * 1.15

    def to_px(panel, x, y, ylo, yhi):
        x0, y0, x1, y1 = panel
        return (int(x0 + (x1 - x0) * x / xmax), int(y1 - (y1 - y0) * (y - ylo) / max(yhi - ylo, 1e-9)))

    for panel, title, (ylo, yhi) in zip(panels, ("train loss (one step every 10)", "val mIoU % (camera mask)"),
                                        ((lmin, lmax), (0, mmax)), strict=True):
        x0, y0, x1, y1 = panel
        cv2.rectangle(img, (x0, y0), (x1, y1), (0, 0, 0), 1)
        cv2.putText(img, title, (x0, y0 - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, "samples seen", (x1 - 110, y1 + 35), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        for k in range(5):
            v = ylo + (yhi - ylo) * k / 4
            _, py = to_px(panel, 0, v, ylo, yhi)
            cv2.putText(img, f"{v:.1f}", (x0 - 50, py + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
            px, _ = to_px(panel, xmax * k / 4, ylo, ylo, yhi)
            cv2.putText(img, f"{xmax * k / 4:.0f}", (px - 10, y1 + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    for c, colour in zip(curves, colours, strict=False):
        name = "noise images" if c["noise_images"] else "camera images"
        pts = [to_px(panels[0], x, v, lmin, lmax) for x, v in c["loss"]]
        if len(pts) > 1:
            cv2.polylines(img, [np.array(pts, np.int32)], False, colour, 2, cv2.LINE_AA)
        mp = [to_px(panels[1], p["samples_seen"], 100 * p["miou"], 0, mmax) for p in c["points"]]
        if len(mp) > 1:
            cv2.polylines(img, [np.array(mp, np.int32)], False, colour, 2, cv2.LINE_AA)
        for q in mp:
            cv2.circle(img, q, 4, colour, -1)
        k = curves.index(c)
        cv2.putText(img, name, (panels[1][0] + 10, panels[1][1] + 20 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    if baseline_miou is not None:
        _, py = to_px(panels[1], 0, 100 * baseline_miou, 0, mmax)
        cv2.line(img, (panels[1][0], py), (panels[1][2], py), (120, 120, 120), 1, cv2.LINE_AA)
        cv2.putText(img, f"image-free baseline {100 * baseline_miou:.2f}%", (panels[1][0] + 10, py - 6),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (90, 90, 90), 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("baseline", help="image-free baseline val mIoU")
    b.add_argument("--store", required=True)
    b.add_argument("--json", type=Path)
    c = sub.add_parser("curve", help="evaluate run checkpoints and draw the curve")
    c.add_argument("--store", required=True)
    c.add_argument("--run", type=Path, action="append", required=True)
    c.add_argument("--baseline", type=Path, help="JSON written by the baseline command")
    c.add_argument("--png", type=Path, default=Path("train_curve.png"))
    c.add_argument("--rayiou", action="store_true", help="also RayIoU (slower)")
    c.add_argument("--workers", type=int, default=1)
    c.add_argument("--every", type=int, default=1, help="score every k-th checkpoint (and the last)")
    c.add_argument("--json", type=Path)
    args = ap.parse_args()
    record = machine()
    t0 = time.perf_counter()
    if args.cmd == "baseline":
        out = baseline(args.store)
        print(f"image-free baseline (per-voxel most frequent training label): val mIoU "
              f"{100 * out['miou_camera_mask']:.2f}% (camera mask), {100 * out['miou_no_mask']:.2f}% (no mask); "
              f"{out['train_samples']} train / {out['val_samples']} val samples")
    else:
        base = json.loads(args.baseline.read_text())["miou_camera_mask"] if args.baseline else None
        curves = [run_curve(r, args.store, args.rayiou, args.workers, max(1, args.every)) for r in args.run]
        plot(curves, base, args.png)
        out = {"baseline_miou_camera_mask": base, "runs": curves}
        for cv in curves:
            pts = ", ".join(f"{p['samples_seen']}: {100 * p['miou']:.2f}%" for p in cv["points"])
            print(f"{cv['run']} ({'noise' if cv['noise_images'] else 'images'}): val mIoU by samples seen {pts}")
        print(f"wrote {args.png}")
    out["machine"] = record
    out["seconds"] = time.perf_counter() - t0
    if args.json:
        write_json(out, args.json, indent=1)


if __name__ == "__main__":
    main()
