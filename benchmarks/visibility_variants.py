"""Which camera-visibility definition reproduces Occ3D's `mask_camera`? Every variant tried, scored.

Research: the search that chose the mask definition (docs/visibility.md); the product's masks are
`occdata.visibility`. Kept to rerun the comparison; indexed in benchmarks/README.md.

Input: the real Occ3D label (`semantics`, `mask_lidar`, `mask_camera`) and the camera rig of the real
nuScenes keyframe (nominal calibration: the label's sample is unknown, the cameras are rigid on
the car). Each variant predicts a camera mask from the label's semantics (+ mask_lidar where it says
so); it is scored against the label's `mask_camera` by IoU over all voxels / occupied / free, and
precision / recall on occupied voxels. No variant uses the label's `mask_camera`.

    ./.venv/bin/python -m benchmarks.visibility_variants [--json]

The exploratory kernels live here (benchmark code) and step through the grid with the package's own
traversal (`occdata.sensors.raycast`, the DDA the masks use); the settled definition is
`occdata.visibility.camera_mask` (the row marked "settled").
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from numba import njit, prange

from benchmarks.common import OCC3D_LABEL as LABEL
from benchmarks.common import REAL_NUSCENES as ROOT
from benchmarks.provenance import machine
from occdata.constants import FREE_LABEL, GRID
from occdata.formats.occ3d import read_label
from occdata.sensors.raycast import segment_advance, segment_setup
from occdata.visibility import GROUND_CLASSES, camera_mask
from occdata.visibility.check import rig_of_sample

__all__ = ["Lab", "run"]

# A pixel ray's far end: |d| >= 1 (unit depth along the optical axis), so 256 m passes the grid's
# ~115 m diagonal from any camera inside it.
BEYOND_GRID = 256.0
LOWER = np.asarray(GRID.lower, np.float64)
VS = GRID.voxel_size
CENTRE = np.zeros((1, 3))
CORNERS = np.array([[sx, sy, sz] for sx in (-0.45, 0.45) for sy in (-0.45, 0.45) for sz in (-0.45, 0.45)])


@njit(cache=True)
def _start(a, b, lower, vs, shape):  # noqa: ANN001, ANN202
    """A fresh traversal of segment a -> b with the package's DDA: (non-empty, t at b, start voxel,
    step, next boundary t, boundary spacing t) (the last four: (3,) arrays `segment_advance` updates)."""
    idx = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_next = np.empty(3)
    t_delta = np.empty(3)
    ok, t_end = segment_setup(a, b, lower, vs, shape, idx, step, t_next, t_delta)
    return ok, t_end, idx, step, t_next, t_delta


@njit(cache=True)
def _entry_t(step, t_next, t_delta):  # noqa: ANN001, ANN202
    """Where the segment enters the start voxel of a fresh `segment_setup`: the last of its slab
    crossings, or 0 when it starts inside (the cameras do)."""
    t = 0.0
    for q in range(3):
        if step[q] != 0:
            t = max(t, t_next[q] - t_delta[q])
    return t


@njit(cache=True)
def _count_before(occ, shape, a, b, target, lower, vs, cap):  # noqa: ANN001, ANN202
    """Occupied voxels on segment a -> b (b inside voxel `target`) before the target, and the metres
    from the first one's entry to b (-1 if none); (cap + 1, inf) = gave up or never reached.

    The traversal is the package's own (`occdata.sensors.raycast`), so the variants below step
    exactly as the settled `camera_mask` does; only what is counted differs."""
    ok, t_end, idx, step, t_next, t_delta = _start(a, b, lower, vs, shape)
    if not ok:
        return cap + 1, np.inf
    L = np.sqrt(((b - a) ** 2).sum())
    cnt = 0
    t = _entry_t(step, t_next, t_delta)
    first = -1.0
    while t <= t_end:
        if idx[0] == target[0] and idx[1] == target[1] and idx[2] == target[2]:
            return cnt, (L - first * L) if first >= 0 else -1.0
        if occ[idx[0], idx[1], idx[2]]:
            if first < 0:
                first = t
            cnt += 1
            if cnt > cap:
                return cap + 1, np.inf
        t = segment_advance(idx, step, t_next, t_delta, shape)
    return cap + 1, np.inf


@njit(cache=True, parallel=True)
def _count_targets(occ, targets, cam, lower, vs, offsets, cap):  # noqa: ANN001, ANN202
    """Per target: min over offsets of (occupied voxels before it, metres behind the first one)."""
    shape = np.array(occ.shape, np.int64)
    n_out = np.empty(len(targets), np.int64)
    gap_out = np.empty(len(targets))
    for n in prange(len(targets)):
        b = np.empty(3)
        best, gap = cap + 1, np.inf
        for o in range(offsets.shape[0]):
            for q in range(3):
                b[q] = lower[q] + (targets[n, q] + 0.5 + offsets[o, q]) * vs
            c, g = _count_before(occ, shape, cam, b, targets[n], lower, vs, cap)
            best = min(best, c)
            gap = min(gap, g)
        n_out[n] = best
        gap_out[n] = gap
    return n_out, gap_out


@njit(cache=True)
def _march_mark(occ, out, a, b, lower, vs, max_hits):  # noqa: ANN001, ANN202
    """Mark voxels along segment a -> b, up to and including the max_hits-th occupied one (the
    package's traversal, as in `_count_before`)."""
    shape = np.array(occ.shape, np.int64)
    ok, t_end, idx, step, t_next, t_delta = _start(a, b, lower, vs, shape)
    if not ok:
        return
    hits = 0
    while True:
        out[idx[0], idx[1], idx[2]] = 1
        if occ[idx[0], idx[1], idx[2]]:
            hits += 1
            if hits >= max_hits:
                return
        if segment_advance(idx, step, t_next, t_delta, shape) > t_end:
            return


@njit(cache=True)
def _pixel_rays(occ, Kinv, R_grid_from_cam, cam, W, H, stride, lower, vs, max_hits):  # noqa: ANN001, ANN202
    out = np.zeros(occ.shape, np.uint8)
    d = np.empty(3)
    v = stride / 2.0 - 0.5
    while v < H - 0.5:
        u = stride / 2.0 - 0.5
        while u < W - 0.5:
            r0 = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
            r1 = Kinv[1, 1] * v + Kinv[1, 2]
            for q in range(3):
                d[q] = R_grid_from_cam[q, 0] * r0 + R_grid_from_cam[q, 1] * r1 + R_grid_from_cam[q, 2]
            _march_mark(occ, out, cam, cam + BEYOND_GRID * d, lower, vs, max_hits)
            u += stride
        v += stride
    return out


@njit(cache=True)
def _rays_to_targets(occ, targets, cam, lower, vs):  # noqa: ANN001, ANN202
    """The Occ3D paper's wording: a ray from the camera centre to each target voxel centre marks the
    voxels up to and including the first occupied one."""
    out = np.zeros(occ.shape, np.uint8)
    b = np.empty(3)
    for n in range(len(targets)):
        for q in range(3):
            b[q] = lower[q] + (targets[n, q] + 0.5) * vs
        _march_mark(occ, out, cam, b, lower, vs, 1)
    return out


class Lab:
    """The label, its derived masks and the rig; `score` turns a predicted mask into a table row."""

    def __init__(self) -> None:
        lab = read_label(LABEL, require_masks=True)
        self.sem = lab["semantics"]
        self.ml = lab["mask_lidar"].astype(bool)
        self.mc = lab["mask_camera"].astype(bool)
        self.occ = self.sem != FREE_LABEL
        self.flat = np.isin(self.sem, GROUND_CLASSES)
        self.K, self.T, self.size = rig_of_sample(ROOT, None, None)
        self.cams = [-(T[:3, :3].T @ T[:3, 3]) for T in self.T]
        self.rows: list[dict[str, object]] = []

    def in_image(self, idx: np.ndarray, c: int, top: float = 0.0, bottom: float = 0.0, side: float = 0.0) -> np.ndarray:
        p = (LOWER + (idx + 0.5) * VS) @ self.T[c][:3, :3].T + self.T[c][:3, 3]
        W, H = self.size[c]
        with np.errstate(all="ignore"):
            u = self.K[c][0, 0] * p[:, 0] / p[:, 2] + self.K[c][0, 2]
            v = self.K[c][1, 1] * p[:, 1] / p[:, 2] + self.K[c][1, 2]
        return (p[:, 2] > 0) & (u >= -0.5 - side) & (u < W - 0.5 + side) & (v >= -0.5 - top) & (v < H - 0.5 + bottom)

    def counts(self, occluders: np.ndarray, idx: np.ndarray, offsets: np.ndarray, cap: int = 40,
               **frustum: float) -> tuple[np.ndarray, np.ndarray]:
        """Min over cameras (seeing the target) of occluders before it, and of metres behind the first one."""
        best = np.full(len(idx), cap + 1)
        gap = np.full(len(idx), np.inf)
        for c in range(len(self.T)):
            ii = self.in_image(idx, c, **frustum)
            n, g = _count_targets(occluders.astype(np.uint8), idx[ii], self.cams[c], LOWER, VS, offsets, cap)
            best[ii] = np.minimum(best[ii], n)
            gap[ii] = np.minimum(gap[ii], g)
        return best, gap

    def mask_of(self, idx: np.ndarray, keep: np.ndarray) -> np.ndarray:
        m = np.zeros(self.sem.shape, bool)
        m[tuple(idx[keep].T)] = True
        return m

    def score(self, name: str, pred: np.ndarray, group: str) -> None:
        pred = pred.astype(bool)

        def iou(a: np.ndarray, b: np.ndarray) -> float:
            u = (a | b).sum()
            return float((a & b).sum() / u) if u else 1.0

        occ, mc = self.occ, self.mc
        tp = (pred & mc & occ).sum()
        row = {"group": group, "variant": name, "iou_all": iou(pred, mc), "iou_occupied": iou(pred & occ, mc & occ),
               "iou_free": iou(pred & ~occ, mc & ~occ), "occ_precision": float(tp / max((pred & occ).sum(), 1)),
               "occ_recall": float(tp / max((mc & occ).sum(), 1))}
        self.rows.append(row)
        print(f"{group:9s} {name:74s} {row['iou_all']:.3f} {row['iou_occupied']:.3f} {row['iou_free']:.3f}"
              f"  {row['occ_precision']:.3f} {row['occ_recall']:.3f}", flush=True)


def run(lab: Lab) -> None:
    occ, ml, flat = lab.occ, lab.ml, lab.flat
    obj = occ & ~flat
    occ_u8 = occ.astype(np.uint8)
    print(f"{'group':9s} {'variant':74s} {'all':5s} {'occ':5s} {'free':5s}  {'occP':5s} {'occR':5s}")

    # 1. Strict occlusion, every voxel tested (the project's old definition), and no occlusion at all.
    every = np.argwhere(np.ones(occ.shape, bool))
    n_all, _ = lab.counts(occ, every, CENTRE, cap=0)
    strict = (n_all == 0).reshape(occ.shape)
    lab.score("old: centre ray, no occupied voxel strictly before it (all voxels)", strict, "strict")
    lab.score("old, AND mask_lidar", strict & ml, "strict")
    in_any = np.zeros(len(every), bool)
    for c in range(len(lab.T)):
        in_any |= lab.in_image(every, c)
    lab.score("no occlusion: centre inside some image, AND mask_lidar", in_any.reshape(occ.shape) & ml, "no-occl")

    # 2. The paper's wording: rays from each camera centre to each occupied voxel centre.
    for frustum in (True, False):
        m = np.zeros(occ.shape, bool)
        for c in range(len(lab.T)):
            tgt = np.argwhere(occ)
            if frustum:
                tgt = tgt[lab.in_image(tgt, c)]
            m |= _rays_to_targets(occ_u8, tgt.astype(np.int64), lab.cams[c], LOWER, VS).astype(bool)
        where = "targets inside the image" if frustum else "every occupied target"
        lab.score(f"paper: rays to occupied centres, up to+incl. first occupied ({where}), AND mask_lidar",
                  m & ml, "paper")

    # 3. Rays through image pixels, marking up to and including the n-th occupied voxel.
    for stride in (8, 4, 2):
        for hits in (1, 2, 4, 6, 8, 10):
            m = np.zeros(occ.shape, bool)
            for c in range(len(lab.T)):
                W, H = lab.size[c]
                m |= _pixel_rays(occ_u8, np.linalg.inv(lab.K[c]), lab.T[c][:3, :3].T.copy(), lab.cams[c], int(W),
                                 int(H), float(stride), LOWER, VS, hits).astype(bool)
            lab.score(f"pixel rays every {stride} px, up to+incl. occupied voxel #{hits}, AND mask_lidar", m & ml,
                      "pixel")

    # 4. Per-voxel rays with a tolerance: visible if <= N occupied voxels lie before it (min over cameras).
    tgt = np.argwhere(ml)
    t_flat, t_free = lab.flat[tuple(tgt.T)], ~occ[tuple(tgt.T)]
    exposed = occ.copy()
    pad = np.pad(occ, 1)
    for ax in range(3):
        for s in (1, -1):
            exposed &= np.roll(pad, s, axis=ax)[1:-1, 1:-1, 1:-1]
    exposed = occ & ~exposed  # occupied with a free 6-neighbour
    cases = {
        "centre ray, all occupied occlude": lab.counts(occ, tgt, CENTRE),
        "centre ray, object (non-ground) voxels occlude": lab.counts(obj, tgt, CENTRE),
        "centre ray, only surface (exposed) voxels occlude": lab.counts(exposed, tgt, CENTRE),
        "best of 8 corner rays, all occupied occlude": lab.counts(occ, tgt, CORNERS),
        "best of 8 corner rays, object voxels occlude": lab.counts(obj, tgt, CORNERS),
        "centre ray, object voxels occlude, image +50 px (+200 below)": lab.counts(obj, tgt, CENTRE, top=50.0,
                                                                                   side=50.0, bottom=200.0),
        "centre ray, object voxels occlude, no lower image edge": lab.counts(obj, tgt, CENTRE, bottom=1e9),
    }
    for name, (n, _) in cases.items():
        for N in (0, 2, 4, 6, 7, 8, 10):
            lab.score(f"every voxel tested: {name}, N={N}, within mask_lidar", lab.mask_of(tgt, n <= N), "tolerance")
    for name, (n, _) in cases.items():
        for N in (0, 2, 4, 6, 7, 8, 10):
            lab.score(f"free+ground = mask_lidar; objects: {name}, N={N}", lab.mask_of(tgt, (n <= N) | t_flat | t_free),
                      "objects")
    n, _ = cases["centre ray, object (non-ground) voxels occlude"]
    for N in (4, 7, 10):
        lab.score(f"ground = mask_lidar; objects+free: centre ray, object voxels occlude, N={N}",
                  lab.mask_of(tgt, (n <= N) | t_flat), "objects")
    # Depth tolerance instead of a count: visible if <= D metres behind the first occupied voxel.
    _, gap = cases["centre ray, object (non-ground) voxels occlude"]
    _, gap_c = cases["best of 8 corner rays, object voxels occlude"]
    for D in (0.5, 1.0, 2.0, 3.0, 4.0, 6.0):
        lab.score(f"free+ground = mask_lidar; objects: centre ray <= {D} m behind first object voxel",
                  lab.mask_of(tgt, (gap <= D) | t_flat | t_free), "depth")
        lab.score(f"free+ground = mask_lidar; objects: corner rays <= {D} m behind first object voxel",
                  lab.mask_of(tgt, (gap_c <= D) | t_flat | t_free), "depth")

    # Facts the settled definition rests on.
    mc = lab.mc
    print("\nfacts: camera-visible but not LiDAR-observed:", int((mc & ~ml).sum()),
          "| ground voxels with mask_camera != mask_lidar:", int((mc != ml)[flat].sum()), "of", int(flat.sum()),
          "| free voxels with mask_camera != mask_lidar:", int((mc != ml)[~occ].sum()), "of", int((~occ).sum()),
          "| object voxels LiDAR-observed:", int(ml[obj].sum()), "of", int(obj.sum()))
    n_obj, _ = lab.counts(obj, np.argwhere(obj), CENTRE)
    v_obj = mc[obj]
    print("object voxels by object voxels crossed on the best camera ray: count, voxels, visible fraction")
    for k in range(16):
        sel = n_obj == k
        print(f"  {k:2d} {int(sel.sum()):6d} {v_obj[sel].mean():.3f}")
    sel = (n_obj >= 16) & (n_obj <= 40)
    print(f"  16-40 {int(sel.sum()):6d} {v_obj[sel].mean():.3f}; not seen by any camera or > 40: "
          f"{int((n_obj > 40).sum())} voxels, visible {v_obj[n_obj > 40].mean():.3f}\n")

    # 5. The settled definition, through the library function.
    settled = camera_mask(lab.sem, lab.ml.astype(np.uint8), lab.K, lab.T, lab.size, LOWER, VS)
    lab.score("settled: occdata.visibility.camera_mask (objects: centre ray, <= 7 object voxels)", settled, "settled")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="also print rows + machine record as one JSON object")
    args = ap.parse_args()
    record = machine()
    lab = Lab()
    run(lab)
    if args.json:
        print(json.dumps({"machine": record, "rows": lab.rows}))


if __name__ == "__main__":
    main()
