"""Which camera-visibility definition reproduces Occ3D's `mask_camera`? Every variant tried, scored.

Input: the real Occ3D label (`semantics`, `mask_lidar`, `mask_camera`) and the camera rig of the real
nuScenes keyframe (nominal calibration: the label's sample is unknown, the cameras are rigid on
the car). Each variant predicts a camera mask from the label's semantics (+ mask_lidar where it says
so); it is scored against the label's `mask_camera` by IoU over all voxels / occupied / free, and
precision / recall on occupied voxels. No variant uses the label's `mask_camera`.

    ./.venv/bin/python benchmarks/visibility_variants.py [--json]

The exploratory kernels live here (benchmark code); the settled definition is
`occdata.visibility.camera_mask` (the row marked "settled").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from numba import njit, prange

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from occdata.constants import FREE_LABEL, GRID  # noqa: E402
from occdata.visibility import GROUND_CLASSES, camera_mask  # noqa: E402
from occdata.visibility.check import load_occ3d_label, rig_of_sample  # noqa: E402

DATA = REPO.parent / "shared" / "data"
LABEL = DATA / "occ3d-label" / "29796060110c4163b07f06eff4af0753" / "labels.npz"
ROOT = DATA / "nuscenes-real"
LOWER = np.asarray(GRID.lower, np.float64)
VS = GRID.voxel_size
CENTRE = np.zeros((1, 3))
CORNERS = np.array([[sx, sy, sz] for sx in (-0.45, 0.45) for sy in (-0.45, 0.45) for sz in (-0.45, 0.45)])


@njit(cache=True)
def _count_before(occ, a, b, ti, tj, tk, lower, vs, cap):  # noqa: ANN001, ANN202
    """Occupied voxels on segment a -> b before voxel (ti, tj, tk) (cap + 1 = gave up / never reached)."""
    X, Y, Z = occ.shape
    d = b - a
    t0 = 0.0
    for q in range(3):
        if abs(d[q]) < 1e-15:
            continue
        ta = (lower[q] - a[q]) / d[q]
        tb = (lower[q] + occ.shape[q] * vs - a[q]) / d[q]
        t0 = max(t0, min(ta, tb))
    i = min(max(int(np.floor((a[0] + t0 * d[0] - lower[0]) / vs)), 0), X - 1)
    j = min(max(int(np.floor((a[1] + t0 * d[1] - lower[1]) / vs)), 0), Y - 1)
    k = min(max(int(np.floor((a[2] + t0 * d[2] - lower[2]) / vs)), 0), Z - 1)
    si = 1 if d[0] > 0 else -1 if d[0] < 0 else 0
    sj = 1 if d[1] > 0 else -1 if d[1] < 0 else 0
    sk = 1 if d[2] > 0 else -1 if d[2] < 0 else 0
    ni = (lower[0] + (i + (si > 0)) * vs - a[0]) / d[0] if si != 0 else np.inf
    nj = (lower[1] + (j + (sj > 0)) * vs - a[1]) / d[1] if sj != 0 else np.inf
    nk = (lower[2] + (k + (sk > 0)) * vs - a[2]) / d[2] if sk != 0 else np.inf
    di = vs / abs(d[0]) if si != 0 else np.inf
    dj = vs / abs(d[1]) if sj != 0 else np.inf
    dk = vs / abs(d[2]) if sk != 0 else np.inf
    L = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    cnt = 0
    t = t0
    first = -1.0
    for _ in range(4000):
        if i == ti and j == tj and k == tk:
            return cnt, (L - first * L) if first >= 0 else -1.0
        if occ[i, j, k]:
            if first < 0:
                first = t
            cnt += 1
            if cnt > cap:
                return cap + 1, np.inf
        if ni <= nj and ni <= nk:
            t = ni
            i += si
            ni += di
            if i < 0 or i >= X:
                break
        elif nj <= nk:
            t = nj
            j += sj
            nj += dj
            if j < 0 or j >= Y:
                break
        else:
            t = nk
            k += sk
            nk += dk
            if k < 0 or k >= Z:
                break
    return cap + 1, np.inf


@njit(cache=True, parallel=True)
def _count_targets(occ, targets, cam, lower, vs, offsets, cap):  # noqa: ANN001, ANN202
    """Per target: min over offsets of (occupied voxels before it, metres behind the first one)."""
    n_out = np.empty(len(targets), np.int64)
    gap_out = np.empty(len(targets))
    for n in prange(len(targets)):
        b = np.empty(3)
        best, gap = cap + 1, np.inf
        for o in range(offsets.shape[0]):
            for q in range(3):
                b[q] = lower[q] + (targets[n, q] + 0.5 + offsets[o, q]) * vs
            c, g = _count_before(occ, cam, b, targets[n, 0], targets[n, 1], targets[n, 2], lower, vs, cap)
            best = min(best, c)
            gap = min(gap, g)
        n_out[n] = best
        gap_out[n] = gap
    return n_out, gap_out


@njit(cache=True)
def _march_mark(occ, out, a, d, t_max, lower, vs, max_hits):  # noqa: ANN001, ANN202
    """Mark voxels along a + t d, 0 <= t <= t_max, up to and including the max_hits-th occupied one."""
    X, Y, Z = occ.shape
    t0, t1 = 0.0, t_max
    for q in range(3):
        if abs(d[q]) < 1e-15:
            if a[q] < lower[q] or a[q] >= lower[q] + occ.shape[q] * vs:
                return
            continue
        ta = (lower[q] - a[q]) / d[q]
        tb = (lower[q] + occ.shape[q] * vs - a[q]) / d[q]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    if t0 > t1:
        return
    i = min(max(int(np.floor((a[0] + t0 * d[0] - lower[0]) / vs)), 0), X - 1)
    j = min(max(int(np.floor((a[1] + t0 * d[1] - lower[1]) / vs)), 0), Y - 1)
    k = min(max(int(np.floor((a[2] + t0 * d[2] - lower[2]) / vs)), 0), Z - 1)
    si = 1 if d[0] > 0 else -1 if d[0] < 0 else 0
    sj = 1 if d[1] > 0 else -1 if d[1] < 0 else 0
    sk = 1 if d[2] > 0 else -1 if d[2] < 0 else 0
    ni = (lower[0] + (i + (si > 0)) * vs - a[0]) / d[0] if si != 0 else np.inf
    nj = (lower[1] + (j + (sj > 0)) * vs - a[1]) / d[1] if sj != 0 else np.inf
    nk = (lower[2] + (k + (sk > 0)) * vs - a[2]) / d[2] if sk != 0 else np.inf
    di = vs / abs(d[0]) if si != 0 else np.inf
    dj = vs / abs(d[1]) if sj != 0 else np.inf
    dk = vs / abs(d[2]) if sk != 0 else np.inf
    hits = 0
    t = t0
    while t <= t1:
        out[i, j, k] = 1
        if occ[i, j, k]:
            hits += 1
            if hits >= max_hits:
                return
        if ni <= nj and ni <= nk:
            t = ni
            i += si
            ni += di
            if i < 0 or i >= X:
                return
        elif nj <= nk:
            t = nj
            j += sj
            nj += dj
            if j < 0 or j >= Y:
                return
        else:
            t = nk
            k += sk
            nk += dk
            if k < 0 or k >= Z:
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
            _march_mark(occ, out, cam, d, 1e9, lower, vs, max_hits)
            u += stride
        v += stride
    return out


@njit(cache=True)
def _rays_to_targets(occ, targets, cam, lower, vs):  # noqa: ANN001, ANN202
    """The Occ3D paper's wording: a ray from the camera centre to each target voxel centre marks the
    voxels up to and including the first occupied one."""
    out = np.zeros(occ.shape, np.uint8)
    d = np.empty(3)
    for n in range(len(targets)):
        for q in range(3):
            d[q] = lower[q] + (targets[n, q] + 0.5) * vs - cam[q]
        _march_mark(occ, out, cam, d, 1.0, lower, vs, 1)
    return out


class Lab:
    """The label, its derived masks and the rig; `score` turns a predicted mask into a table row."""

    def __init__(self) -> None:
        lab = load_occ3d_label(LABEL)
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
    ap.add_argument("--json", action="store_true", help="also print all rows as one JSON list at the end")
    args = ap.parse_args()
    lab = Lab()
    run(lab)
    if args.json:
        print(json.dumps(lab.rows))


if __name__ == "__main__":
    main()
