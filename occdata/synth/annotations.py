"""Box annotations and nuScenes-lidarseg labels of the synthetic world (docs/design.md#labels-from-lidar).

Box-annotated objects: every actor while it is on the road path, and every static object of a
nuScenes box category (parked cars and motorcycles, barriers, cones, parked bicycles; nuScenes
boxes these whether they move or not). A box is the tight yaw-oriented box around all parts of the
object in its own heading frame: translation = box centre (global, z included), size =
[width, length, height], rotation = the yaw quaternion (wxyz).

LiDAR points and boxes: a return counts for a box when it lies within `POINT_MARGIN` of the box,
except returns less than `POINT_MARGIN` above the box's bottom face: the bottom of every box is the
ground plane z = 0, and ground returns beside a pedestrian's cylinder or under a truck's trailer
are not returns of the object. The margin absorbs float32 rounding of the stored points, which lie
exactly on the box faces.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from occdata.geometry import invert_rigid, points_in_box
from occdata.synth.tables import make_token
from occdata.synth.world import BOX, P_COS, P_CX, P_CY, P_HX, P_HY, P_SIN, P_TYPE, P_Z0, P_Z1, SceneWorld, place_parts

__all__ = [
    "KIND_CATEGORY",
    "LIDARSEG_FROM_OCC3D",
    "POINT_MARGIN",
    "KeyframeAnnotation",
    "ObjectBoxes",
    "annotate_keyframe",
    "annotation_rows",
    "object_boxes",
    "object_parts",
    "object_velocities",
    "points_in_boxes",
    "rays_hit_parts",
    "visibility_levels",
]

POINT_MARGIN = 0.01  # m, see the module docstring

# Occ3D class (occdata.constants.CLASS_NAMES, 0..17) -> lidarseg index: one category per class (the
# inverse of the challenge mapping); `others` -> static.other; free never labels a return.
LIDARSEG_FROM_OCC3D = np.array([29, 9, 14, 16, 17, 18, 21, 2, 12, 22, 23, 24, 25, 26, 27, 28, 30, 0], np.uint8)

# Object kind (occdata.synth.world templates) -> nuScenes category.
KIND_CATEGORY = {
    "car": "vehicle.car", "truck": "vehicle.truck", "bus": "vehicle.bus.rigid", "bicycle": "vehicle.bicycle",
    "motorcycle": "vehicle.motorcycle", "pedestrian": "human.pedestrian.adult",
    "cone": "movable_object.trafficcone", "barrier": "movable_object.barrier",
}

_VISIBILITY_BOUNDS = (0.4, 0.6, 0.8)  # visibility tokens "1".."4": 0-40%, 40-60%, 60-80%, 80-100%


@dataclass(frozen=True, eq=False)
class ObjectBoxes:
    """Boxes of the box-annotated objects present at one timestamp, in one frame (global unless
    converted with `to_frame`): `keys` object identities ("static-<i>" / "actor-<i>", stable over
    time), `kinds` template names (car, truck, bus, bicycle, motorcycle, pedestrian, cone, barrier),
    `center (B, 3) float64`, `size_wlh (B, 3) float64` (width, length, height), `yaw (B,) float64`
    in (-pi, pi] (heading of the box's length axis), `speed (B,) float64` m/s (0: static or
    standing)."""

    keys: tuple[str, ...]
    kinds: tuple[str, ...]
    center: np.ndarray
    size_wlh: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def moving(self) -> np.ndarray:
        """`(B,) bool`: the object moves (speed > 0)."""
        return self.speed > 0

    def to_frame(self, T_frame_from_global: np.ndarray) -> ObjectBoxes:
        """The boxes in another frame related to global by a yaw-only rigid transform `(4, 4)` (an
        inverted ego pose, e.g. key ego: `invert_rigid(T_global_from_keyego)`)."""
        T = np.asarray(T_frame_from_global, np.float64)
        center = self.center @ T[:3, :3].T + T[:3, 3]
        yaw = np.angle(np.exp(1j * (self.yaw + np.arctan2(T[1, 0], T[0, 0]))))
        return ObjectBoxes(self.keys, self.kinds, center, self.size_wlh.copy(), yaw, self.speed.copy())


def _local_box(parts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tight box of parts `(K, 9)` in their local frame: centre `(3,)` and extent `(3,)` (x, y, z)."""
    c, s = np.abs(parts[:, P_COS]), np.abs(parts[:, P_SIN])
    ex = c * parts[:, P_HX] + s * parts[:, P_HY]  # cylinders: cos 1, sin 0, hx = hy = radius
    ey = s * parts[:, P_HX] + c * parts[:, P_HY]
    lo = np.array([(parts[:, P_CX] - ex).min(), (parts[:, P_CY] - ey).min(), parts[:, P_Z0].min()])
    hi = np.array([(parts[:, P_CX] + ex).max(), (parts[:, P_CY] + ey).max(), parts[:, P_Z1].max()])
    return (lo + hi) / 2, hi - lo


def _posed_box(parts: np.ndarray, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Global box of parts posed at (x, y, yaw): centre `(3,)`, size (w, l, h) `(3,)`, yaw in (-pi, pi]."""
    mid, ext = _local_box(parts)
    c, s = np.cos(yaw), np.sin(yaw)
    center = np.array([x + c * mid[0] - s * mid[1], y + s * mid[0] + c * mid[1], mid[2]])
    return center, np.array([ext[1], ext[0], ext[2]]), float(np.arctan2(s, c))


def object_boxes(world: SceneWorld, t_us: int) -> ObjectBoxes:
    """Boxes (global frame) of every box-annotated object present at `t_us`: the static objects of
    box kinds, then the actors on the road path at that time (as `SceneWorld.primitives_at`)."""
    keys, kinds, rows, speed = [], [], [], []
    for i, o in enumerate(world.static_objects):
        keys.append(f"static-{i}")
        kinds.append(o.kind)
        rows.append(_posed_box(o.parts, o.x, o.y, o.yaw))
        speed.append(0.0)
    for i, a in enumerate(world.actors):
        if not a.in_world(world.path, t_us):
            continue
        keys.append(f"actor-{i}")
        kinds.append(a.kind)
        rows.append(_posed_box(a.parts, *a.pose_at(world.path, t_us)))
        speed.append(a.speed)
    center = np.array([r[0] for r in rows], np.float64).reshape(-1, 3)
    size = np.array([r[1] for r in rows], np.float64).reshape(-1, 3)
    yaw = np.array([r[2] for r in rows], np.float64)
    return ObjectBoxes(tuple(keys), tuple(kinds), center, size, yaw, np.array(speed, np.float64))


def object_velocities(world: SceneWorld, t_us: int, dt_us: int = 1000) -> np.ndarray:
    """`v_global (B, 3) float64` m/s of the box centre of each object of `object_boxes(world, t_us)`, in
    that order: the true, instantaneous velocity (a centre difference over +-`dt_us` of the actor's
    exact pose along its path); 0 for static objects."""
    out = [np.zeros(3) for _ in world.static_objects]
    for a in world.actors:
        if not a.in_world(world.path, t_us):
            continue
        c0 = _posed_box(a.parts, *a.pose_at(world.path, t_us - dt_us))[0]
        c1 = _posed_box(a.parts, *a.pose_at(world.path, t_us + dt_us))[0]
        out.append((c1 - c0) / (2e-6 * dt_us))
    return np.array(out, np.float64).reshape(-1, 3)


def object_parts(world: SceneWorld, key: str, t_us: int) -> np.ndarray:
    """The primitives `(K, 9) float64` (global) of the object `key` at `t_us`."""
    kind, i = key.split("-")
    if kind == "static":
        o = world.static_objects[int(i)]
        return place_parts(o.parts, o.x, o.y, o.yaw)
    a = world.actors[int(i)]
    return place_parts(a.parts, *a.pose_at(world.path, t_us))


def _box_pose(center: np.ndarray, yaw: float) -> np.ndarray:
    """`T_global_from_box (4, 4)` of a box standing upright at `center (3,)` turned by `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = ((c, -s), (s, c))
    T[:3, 3] = center
    return T


def points_in_boxes(points: np.ndarray, boxes: ObjectBoxes, margin: float = POINT_MARGIN) -> np.ndarray:
    """`(N, B) bool`: point n `(N, 3)` (the boxes' frame) lies in box b: within `margin` of it, but
    more than `margin` above its bottom face (module docstring)."""
    inside = np.zeros((len(points), len(boxes)), bool)
    order = np.argsort(points[:, 0], kind="stable")  # candidates of a box: a slice of the x-sorted points
    xs = points[order, 0]
    for b in range(len(boxes)):
        w, length, h = boxes.size_wlh[b]
        reach = 0.5 * float(np.hypot(w, length)) + margin + 1e-6
        lo, hi = np.searchsorted(xs, [boxes.center[b, 0] - reach, boxes.center[b, 0] + reach])
        cand = order[lo:hi]
        # The margin-grown box raised by `margin`: its bottom face, `margin` above the box's, is open.
        T_box_from_global = invert_rigid(_box_pose(boxes.center[b] + (0.0, 0.0, margin), boxes.yaw[b]))
        half = np.array([length / 2 + margin, w / 2 + margin, h / 2])
        inside[cand, b] = points_in_box(points[cand], T_box_from_global, half) & (
            points[cand, 2] > boxes.center[b, 2] - h / 2 + margin)
    return inside


def _slab(o: np.ndarray | float, d: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter interval `(t_in, t_out)` inside the slab lo <= o + t d <= hi (arrays `(N,)`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    inside = (o >= lo) & (o <= hi)
    t_in = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    t_out = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return t_in, t_out


def rays_hit_parts(origin: np.ndarray, dirs: np.ndarray, parts: np.ndarray, t_max: float) -> np.ndarray:
    """`(N,) bool`: a ray (origin `(3,)`, unit dirs `(N, 3)`, global) meets one of the primitives
    `(K, 9)` (global) within `t_max` when nothing else is in the world."""
    hit = np.zeros(len(dirs), bool)
    for p in parts:
        ox, oy = origin[0] - p[P_CX], origin[1] - p[P_CY]
        z_in, z_out = _slab(origin[2], dirs[:, 2], p[P_Z0], p[P_Z1])
        t_lo, t_hi = np.maximum(z_in, 0.0), np.minimum(z_out, t_max)
        if p[P_TYPE] == BOX:
            c, s = p[P_COS], p[P_SIN]
            for o, d, half in ((c * ox + s * oy, c * dirs[:, 0] + s * dirs[:, 1], p[P_HX]),
                               (-s * ox + c * oy, -s * dirs[:, 0] + c * dirs[:, 1], p[P_HY])):
                t_in, t_out = _slab(o, d, -half, half)
                t_lo, t_hi = np.maximum(t_lo, t_in), np.minimum(t_hi, t_out)
        else:  # vertical cylinder: |(ox, oy) + t (dx, dy)| <= r
            a = dirs[:, 0] ** 2 + dirs[:, 1] ** 2
            bq = ox * dirs[:, 0] + oy * dirs[:, 1]
            disc = bq * bq - a * (ox * ox + oy * oy - p[P_HX] ** 2)
            root = np.sqrt(np.maximum(disc, 0.0))
            safe_a = np.where(a > 0, a, 1.0)
            inside_axis = ox * ox + oy * oy <= p[P_HX] ** 2  # a vertical ray stays at (ox, oy)
            meets = np.where(a > 0, disc >= 0, inside_axis)
            t_lo = np.where(meets, np.maximum(t_lo, np.where(a > 0, (-bq - root) / safe_a, -np.inf)), np.inf)
            t_hi = np.minimum(t_hi, np.where(a > 0, (-bq + root) / safe_a, np.inf))
        hit |= t_lo <= t_hi
    return hit


def visibility_levels(
    world: SceneWorld, t_us: int, boxes: ObjectBoxes, num_points: np.ndarray, origin: np.ndarray,
    dirs: np.ndarray, t_max: float,
) -> np.ndarray:
    """Visibility level `(B,) int` 1..4 (tokens of visibility.json) of each box from the LiDAR: the
    fraction of the rays (origin `(3,)`, unit dirs `(N, 3)`, global) that would meet the object's
    parts if it were alone whose return actually lies in its box (`num_points`). nuScenes rates the
    visible fraction in the camera images; the LiDAR sits close to the cameras, so this is a proxy."""
    levels = np.ones(len(boxes), np.int64)
    for b, key in enumerate(boxes.keys):
        rel = boxes.center[b] - origin
        radius = 0.5 * float(np.linalg.norm(boxes.size_wlh[b])) + 0.01
        if float(np.linalg.norm(rel)) > t_max + radius:
            continue  # out of range: no ray can meet it
        along = dirs @ rel
        near = (along > -radius) & (rel @ rel - along**2 <= radius**2)
        n_alone = int(rays_hit_parts(origin, dirs[near], object_parts(world, key, t_us), t_max).sum())
        if n_alone > 0:
            levels[b] = 1 + int(np.searchsorted(_VISIBILITY_BOUNDS, num_points[b] / n_alone, side="left"))
    return levels


@dataclass(frozen=True, eq=False)
class KeyframeAnnotation:
    """The boxes of one keyframe (global) with their keyframe LiDAR return counts `(B,) int64` and
    visibility levels `(B,) int64` (1..4)."""

    boxes: ObjectBoxes
    num_lidar_pts: np.ndarray
    visibility: np.ndarray


def annotate_keyframe(
    world: SceneWorld, t_us: int, points_global: np.ndarray, origin: np.ndarray, dirs: np.ndarray, t_max: float
) -> KeyframeAnnotation:
    """Boxes at the keyframe LiDAR time `t_us`, counting the keyframe returns `points_global (N, 3)`
    in each; visibility from the sweep's rays (origin `(3,)`, all unit dirs `(M, 3)`, global)."""
    boxes = object_boxes(world, t_us)
    counts = points_in_boxes(points_global, boxes).sum(axis=0).astype(np.int64)
    return KeyframeAnnotation(boxes, counts, visibility_levels(world, t_us, boxes, counts, origin, dirs, t_max))


def _attribute(kind: str, moving: bool) -> str | None:
    if kind in ("car", "truck", "bus"):
        return "vehicle.moving" if moving else "vehicle.parked"
    if kind in ("bicycle", "motorcycle"):
        return "cycle.with_rider" if moving else "cycle.without_rider"
    if kind == "pedestrian":
        return "pedestrian.moving" if moving else "pedestrian.standing"
    return None  # cones, barriers


def _tracks(keyframes: list[KeyframeAnnotation]) -> list[tuple[str, list[int]]]:
    """Each object's contiguous runs of keyframes (one instance per run), in order of first
    appearance: `(key, [k, ...])`."""
    present: dict[str, list[int]] = {}
    for k, kf in enumerate(keyframes):
        for key in kf.boxes.keys:
            present.setdefault(key, []).append(k)
    runs = []
    for key, ks in present.items():
        start = 0
        for n in range(1, len(ks) + 1):
            if n == len(ks) or ks[n] != ks[n - 1] + 1:
                runs.append((key, ks[start:n]))
                start = n
    return runs


def annotation_rows(
    seed: int, scene_index: int, sample_tokens: list[str], keyframes: list[KeyframeAnnotation]
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """`instance` and `sample_annotation` rows of one scene (keyframe k = `sample_tokens[k]`)."""
    instances, annotations = [], []
    index = [{key: b for b, key in enumerate(kf.boxes.keys)} for kf in keyframes]
    for key, ks in _tracks(keyframes):
        inst_tok = make_token(seed, "instance", scene_index, key, ks[0])
        ann_toks = [make_token(seed, "sample_annotation", scene_index, key, k) for k in ks]
        kind = keyframes[ks[0]].boxes.kinds[index[ks[0]][key]]
        instances.append({"token": inst_tok, "category_token": make_token(seed, "category", KIND_CATEGORY[kind]),
                          "nbr_annotations": len(ks), "first_annotation_token": ann_toks[0],
                          "last_annotation_token": ann_toks[-1]})
        for n, k in enumerate(ks):
            kf, b = keyframes[k], index[k][key]
            yaw = kf.boxes.yaw[b]
            attr = _attribute(kind, bool(kf.boxes.moving[b]))
            annotations.append({
                "token": ann_toks[n], "sample_token": sample_tokens[k], "instance_token": inst_tok,
                "visibility_token": str(int(kf.visibility[b])),
                "attribute_tokens": [make_token(seed, "attribute", attr)] if attr else [],
                "translation": [float(v) for v in kf.boxes.center[b]],
                "size": [float(v) for v in kf.boxes.size_wlh[b]],
                "rotation": [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))],
                "prev": ann_toks[n - 1] if n > 0 else "", "next": ann_toks[n + 1] if n + 1 < len(ks) else "",
                "num_lidar_pts": int(kf.num_lidar_pts[b]), "num_radar_pts": 0,
            })
    return instances, annotations
