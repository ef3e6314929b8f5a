"""The synthetic world of one scene: a ground raster plus vertical primitives (boxes, cylinders).

Everything lives in the global frame (x, y on the ground plane z = 0, z up). Two primitive kinds
cover the scene: yaw-oriented boxes (buildings, walls, vehicles, barriers) and vertical cylinders
(poles, tree trunks and crowns, pedestrians, cones). Actors move along the road path; their
primitives are placed at any sensor's own timestamp with `SceneWorld.primitives_at(t_us)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from occdata.synth.trajectory import EgoMotion, Path2D, make_ego_motion, make_path

__all__ = [
    "BOX",
    "CYL",
    "GROUND_CELL",
    "STYLE_GLASS",
    "STYLE_POLE",
    "STYLE_TRUNK",
    "STYLE_WALL",
    "Actor",
    "GroundRaster",
    "Primitives",
    "SceneWorld",
    "StaticObject",
    "make_world",
    "place_parts",
]

BOX, CYL = 0, 1
# Columns of the primitive parameter table `(P, 9) float64`.
P_TYPE, P_CX, P_CY, P_COS, P_SIN, P_HX, P_HY, P_Z0, P_Z1 = range(9)
# Style flags (OR-ed with a 0-7 colour variant) that change shading, never the class.
STYLE_GLASS, STYLE_TRUNK, STYLE_WALL, STYLE_POLE = 16, 32, 64, 128
GROUND_CELL = 0.2  # m per ground raster cell
ROAD_HALF, SIDEWALK_OUT = 5.5, 8.5  # m from a road centre line

# Class ids (occdata.constants.CLASS_NAMES).
BARRIER, BICYCLE, BUS, CAR, MOTORCYCLE, PEDESTRIAN, CONE, TRUCK = 1, 2, 3, 4, 6, 7, 8, 10
DRIVEABLE, OTHER_FLAT, SIDEWALK, TERRAIN, MANMADE, VEGETATION = 11, 12, 13, 14, 15, 16


@dataclass(frozen=True, eq=False)
class Primitives:
    """`params (P, 9) float64` (type, cx, cy, cos yaw, sin yaw, hx or radius, hy, z0, z1),
    `cls (P,) int32` semantic class, `style (P,) int32` shading style (variant | flags)."""

    params: np.ndarray
    cls: np.ndarray
    style: np.ndarray

    @staticmethod
    def empty() -> Primitives:
        return Primitives(np.zeros((0, 9)), np.zeros(0, np.int32), np.zeros(0, np.int32))

    @staticmethod
    def concat(items: list[Primitives]) -> Primitives:
        if not items:
            return Primitives.empty()
        return Primitives(
            np.concatenate([p.params for p in items]).astype(np.float64),
            np.concatenate([p.cls for p in items]).astype(np.int32),
            np.concatenate([p.style for p in items]).astype(np.int32),
        )

    def __len__(self) -> int:
        return len(self.cls)


@dataclass(frozen=True, eq=False)
class GroundRaster:
    """Ground classes on the z = 0 plane: `codes (NY, NX) uint8` = class | (marking << 5)
    (marking 1 = yellow centre line, 2 = white edge line); cell (iy, ix) covers
    x in [x0 + ix*cell, ...), y in [y0 + iy*cell, ...). Outside the raster the ground is terrain."""

    x0: float
    y0: float
    cell: float
    codes: np.ndarray
    road_dist: np.ndarray  # (NY, NX) float32, metres to the nearest road centre line

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """Class `(N,) uint8` at global points `(N, 2)`."""
        ix = np.floor((xy[:, 0] - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((xy[:, 1] - self.y0) / self.cell).astype(np.int64)
        ny, nx = self.codes.shape
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = np.full(len(xy), TERRAIN, np.uint8)
        out[inside] = self.codes[iy[inside], ix[inside]] & 31
        return out

    def dist_at(self, xy: np.ndarray) -> np.ndarray:
        ix = np.clip(np.floor((xy[:, 0] - self.x0) / self.cell).astype(np.int64), 0, self.codes.shape[1] - 1)
        iy = np.clip(np.floor((xy[:, 1] - self.y0) / self.cell).astype(np.int64), 0, self.codes.shape[0] - 1)
        return self.road_dist[iy, ix]


@dataclass(frozen=True, eq=False)
class Actor:
    """A rigid object moving along the road path: parts in its local frame (x forward, y left),
    `parts (K, 9) float64` with the primitive layout (cx, cy local; cos, sin local yaw)."""

    parts: np.ndarray
    cls: np.ndarray
    style: np.ndarray
    s0: float  # arc length at t_ref
    offset: float  # lateral offset (left +)
    speed: float  # m/s along the path direction given by `direction`
    direction: float  # +1 with the path, -1 against it
    t_ref_us: int
    kind: str  # template name: car, truck, bus, bicycle, motorcycle, pedestrian

    def in_world(self, path: Path2D, t_us: int) -> bool:
        """Whether the actor is on the road path at `t_us` (otherwise it is not in the world)."""
        return 0.0 <= self.s_at(t_us) <= path.length

    def s_at(self, t_us: int) -> float:
        return self.s0 + self.direction * self.speed * (t_us - self.t_ref_us) * 1e-6

    def pose_at(self, path: Path2D, t_us: int) -> tuple[float, float, float]:
        s = self.s_at(t_us)
        xy, yaw = path.pose_at(s, self.offset)
        if self.direction < 0:
            yaw = yaw + np.pi
        return float(xy[0]), float(xy[1]), float(yaw)


@dataclass(frozen=True, eq=False)
class StaticObject:
    """A static object of a box-annotated kind (parked car or motorcycle, barrier, cone, parked
    bicycle): its parts `(K, 9) float64` in its local frame (x forward, y left), placed at the
    global (x, y) with heading yaw. Its primitives are part of `SceneWorld.static`."""

    kind: str
    parts: np.ndarray
    x: float
    y: float
    yaw: float


def place_parts(parts: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """Parts `(K, 9)` in a local frame -> global, for a body at (x, y) with heading yaw."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = parts.copy()
    out[:, P_CX] = x + c * parts[:, P_CX] - s * parts[:, P_CY]
    out[:, P_CY] = y + s * parts[:, P_CX] + c * parts[:, P_CY]
    out[:, P_COS] = c * parts[:, P_COS] - s * parts[:, P_SIN]
    out[:, P_SIN] = s * parts[:, P_COS] + c * parts[:, P_SIN]
    return out


def _box(cx: float, cy: float, yaw: float, hx: float, hy: float, z0: float, z1: float) -> list[float]:
    return [BOX, cx, cy, np.cos(yaw), np.sin(yaw), hx, hy, z0, z1]


def _cyl(cx: float, cy: float, r: float, z0: float, z1: float) -> list[float]:
    return [CYL, cx, cy, 1.0, 0.0, r, r, z0, z1]


def _template(kind: str, rng: np.random.Generator) -> tuple[np.ndarray, list[int], list[int]]:
    """Local-frame parts of an object kind: (parts (K, 9), classes, styles)."""
    v = int(rng.integers(0, 8))
    if kind == "car":
        L, W = rng.uniform(4.0, 4.9), rng.uniform(1.75, 1.95)
        return (
            np.array([_box(0, 0, 0, L / 2, W / 2, 0.0, 0.95), _box(-0.25, 0, 0, L * 0.28, W / 2 - 0.08, 0.95, 1.5)]),
            [CAR, CAR],
            [v, v | STYLE_GLASS],
        )
    if kind == "truck":
        return (
            np.array([_box(3.6, 0, 0, 1.1, 1.2, 0.0, 2.9), _box(-1.0, 0, 0, 3.4, 1.25, 0.5, 3.6)]),
            [TRUCK, TRUCK],
            [v | STYLE_GLASS, v],
        )
    if kind == "bus":
        return np.array([_box(0, 0, 0, 5.6, 1.3, 0.0, 3.2)]), [BUS], [v]
    if kind == "bicycle":
        return np.array([_box(0, 0, 0, 0.85, 0.28, 0.0, 1.7)]), [BICYCLE], [v]
    if kind == "motorcycle":
        return np.array([_box(0, 0, 0, 1.05, 0.4, 0.0, 1.5)]), [MOTORCYCLE], [v]
    if kind == "pedestrian":
        return np.array([_cyl(0, 0, 0.28, 0.0, rng.uniform(1.55, 1.9))]), [PEDESTRIAN], [v]
    if kind == "cone":
        return np.array([_cyl(0, 0, 0.18, 0.0, 0.75)]), [CONE], [v]
    if kind == "barrier":
        return np.array([_box(0, 0, 0, 1.0, 0.18, 0.0, 0.95)]), [BARRIER], [v]
    raise ValueError(kind)


@dataclass(frozen=True, eq=False)
class SceneWorld:
    """One scene's world: road path, ego motion, ground raster, static primitives and actors."""

    path: Path2D
    ego: EgoMotion
    ground: GroundRaster
    static: Primitives
    actors: tuple[Actor, ...]
    static_objects: tuple[StaticObject, ...] = ()

    def primitives_at(self, t_us: int) -> Primitives:
        """All primitives (static first, then actors placed at time `t_us`) in the global frame.

        Actors whose arc length has left the road path at that time are not in the world."""
        items = [self.static]
        for a in self.actors:
            if not a.in_world(self.path, t_us):
                continue
            x, y, yaw = a.pose_at(self.path, t_us)
            items.append(Primitives(place_parts(a.parts, x, y, yaw), a.cls, a.style))
        return Primitives.concat(items)

    @property
    def z_top(self) -> float:
        return float(max(self.static.params[:, P_Z1].max(initial=0.0), 5.0))


def _make_ground(rng: np.random.Generator, path: Path2D, margin: float) -> GroundRaster:
    lo = path.xy.min(axis=0) - margin
    hi = path.xy.max(axis=0) + margin
    nx, ny = (np.ceil((hi - lo) / GROUND_CELL)).astype(int)
    canvas = np.ones((ny, nx), np.uint8)

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.round((xy - lo) / GROUND_CELL - 0.5).astype(np.int32).reshape(-1, 1, 2)

    cv2.polylines(canvas, [to_px(path.xy)], False, 0, 1)
    for road in path.extra_roads:
        cv2.polylines(canvas, [to_px(road)], False, 0, 1)
    dist = cv2.distanceTransform(canvas, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float32) * GROUND_CELL
    # Low-frequency patches decide terrain vs other_flat (gravel, parking) off the street.
    coarse = (rng.random((ny // 80 + 2, nx // 80 + 2)) < 0.3).astype(np.uint8)
    patches = np.kron(coarse, np.ones((80, 80), np.uint8))[:ny, :nx]
    codes = np.where(patches > 0, OTHER_FLAT, TERRAIN).astype(np.uint8)
    codes[dist < SIDEWALK_OUT] = SIDEWALK
    codes[dist < ROAD_HALF] = DRIVEABLE
    codes[dist < 0.15] |= 1 << 5
    codes[np.abs(dist - (ROAD_HALF - 0.4)) < 0.12] |= 2 << 5
    return GroundRaster(float(lo[0]), float(lo[1]), GROUND_CELL, codes, dist)


class _Footprints:
    """Occupied ground footprint mask used to keep static objects from overlapping (0.2 m cells)."""

    def __init__(self, ground: GroundRaster) -> None:
        self.g = ground
        self.mask = np.zeros(ground.codes.shape, np.uint8)

    def _px(self, xy: np.ndarray) -> np.ndarray:
        return np.round((xy - [self.g.x0, self.g.y0]) / self.g.cell - 0.5).astype(np.int32)

    def free(self, corners: np.ndarray, min_road_dist: float) -> bool:
        """Whether a convex footprint `(4, 2)` (or circle samples) is clear of roads and other objects."""
        c = corners.mean(axis=0)
        samples = np.concatenate([corners, c[None], (corners + c) / 2, (corners + np.roll(corners, 1, 0)) / 2])
        px = self._px(samples)
        ny, nx = self.mask.shape
        if (px[:, 0] < 0).any() or (px[:, 1] < 0).any() or (px[:, 0] >= nx).any() or (px[:, 1] >= ny).any():
            return False
        if (self.g.dist_at(samples) < min_road_dist).any():
            return False
        poly = np.zeros_like(self.mask)
        cv2.fillConvexPoly(poly, self._px(corners).reshape(-1, 1, 2), 1)
        return not bool((poly & self.mask).any())

    def free_of_objects(self, corners: np.ndarray) -> bool:
        """Whether a convex footprint `(4, 2)` overlaps no object footprint (roads allowed)."""
        poly = np.zeros_like(self.mask)
        cv2.fillConvexPoly(poly, self._px(corners).reshape(-1, 1, 2), 1)
        return not bool((poly & self.mask).any())

    def add(self, corners: np.ndarray) -> None:
        cv2.fillConvexPoly(self.mask, self._px(corners).reshape(-1, 1, 2), 1)


def _rect(cx: float, cy: float, yaw: float, hx: float, hy: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    return np.stack([cx + c * local[:, 0] - s * local[:, 1], cy + s * local[:, 0] + c * local[:, 1]], axis=1)


class _StaticBuilder:
    """Accumulates the static primitives of a scene (rows, classes, styles) and its box-annotated objects."""

    def __init__(self) -> None:
        self.rows: list[list[float]] = []
        self.cls: list[int] = []
        self.sty: list[int] = []
        self.objects: list[StaticObject] = []

    def add(self, parts: np.ndarray, cl: list[int], st: list[int], x: float, y: float, yaw: float,
            kind: str = "") -> None:
        self.rows.extend(place_parts(parts, x, y, yaw).tolist())
        self.cls.extend(cl)
        self.sty.extend(st)
        if kind:  # a box-annotated kind (nuScenes boxes every car, cone, barrier, ..., parked or not)
            self.objects.append(StaticObject(kind, parts, x, y, yaw))

    def primitives(self) -> Primitives:
        return Primitives(np.asarray(self.rows, np.float64).reshape(-1, 9), np.asarray(self.cls, np.int32),
                          np.asarray(self.sty, np.int32))


def _street_furniture(rng: np.random.Generator, path: Path2D, fp: _Footprints, out: _StaticBuilder) -> None:
    """Poles and trees close to the kerb on both sidewalks."""
    L = path.length
    for side in (-1.0, 1.0):
        s = float(rng.uniform(0, 10))
        while s < L:
            (x, y), _ = path.pose_at(s, side * 8.0)
            r = 0.12
            corners = _rect(x, y, 0.0, r, r)
            if fp.free(corners, SIDEWALK_OUT - 0.8):
                fp.add(corners)
                out.add(np.array([_cyl(0, 0, r, 0.0, rng.uniform(5.0, 8.0))]), [MANMADE], [STYLE_POLE], x, y, 0)
            s += float(rng.uniform(18.0, 35.0))
        s = float(rng.uniform(0, 8))
        while s < L:
            (x, y), _ = path.pose_at(s, side * rng.uniform(9.8, 12.5))
            rc = float(rng.uniform(1.3, 2.6))
            crown = _rect(x, y, 0.0, rc, rc)  # the crown's square hull: nothing else may grow into it
            if rng.random() < 0.65 and fp.free(_rect(x, y, 0.0, rc * 0.6, rc * 0.6), SIDEWALK_OUT + 0.3) \
                    and fp.free_of_objects(crown):
                fp.add(crown)
                v = int(rng.integers(0, 8))
                z_c = float(rng.uniform(1.8, 3.0))
                parts = np.array([_cyl(0, 0, 0.2, 0.0, z_c + 0.3), _cyl(0, 0, rc, z_c, z_c + rng.uniform(2.5, 5.0))])
                out.add(parts, [VEGETATION, VEGETATION], [v | STYLE_TRUNK, v], x, y, 0)
            s += float(rng.uniform(5.0, 12.0))


def _buildings_and_walls(rng: np.random.Generator, path: Path2D, fp: _Footprints, out: _StaticBuilder) -> None:
    """Two rows of buildings and some walls along both sides of the street."""
    L = path.length
    for side in (-1.0, 1.0):
        for row_off, gap in ((13.0, (1.0, 6.0)), (38.0, (4.0, 14.0))):
            s = float(rng.uniform(0, 10))
            while s < L:
                hx, hy = float(rng.uniform(3.0, 11.0)), float(rng.uniform(4.0, 10.0))
                off = side * (row_off + hy + rng.uniform(0.0, 5.0))
                (x, y), yaw = path.pose_at(s + hx, off)
                yaw = float(yaw) + rng.uniform(-0.08, 0.08)
                corners = _rect(x, y, yaw, hx, hy)
                if fp.free(corners, SIDEWALK_OUT + 1.5):
                    fp.add(corners)
                    v = int(rng.integers(0, 8))
                    body = np.array([_box(0, 0, 0, hx, hy, 0.0, rng.uniform(6.0, 26.0))])
                    out.add(body, [MANMADE], [v], x, y, yaw)
                s += 2 * hx + float(rng.uniform(*gap))
        s = float(rng.uniform(0, 30))
        while s < L:
            hx = float(rng.uniform(3.0, 8.0))
            (x, y), yaw = path.pose_at(s + hx, side * rng.uniform(9.3, 10.0))
            corners = _rect(x, y, float(yaw), hx, 0.15)
            if rng.random() < 0.5 and fp.free(corners, SIDEWALK_OUT + 0.5):
                fp.add(corners)
                out.add(np.array([_box(0, 0, 0, hx, 0.15, 0.0, rng.uniform(1.5, 3.0))]), [MANMADE], [STYLE_WALL],
                        x, y, float(yaw))
            s += 2 * hx + float(rng.uniform(10.0, 40.0))


def _kerb_slots(rng: np.random.Generator, path: Path2D, out: _StaticBuilder) -> None:
    """Kerb-side slots on the road: parked vehicles, barriers, cones (right side); barriers (left side)."""
    L = path.length
    s = 20.0
    while s < L - 10:
        u = rng.random()
        if u < 0.30:
            kind = "car" if rng.random() < 0.85 else "motorcycle"
            off = -4.2 if kind == "car" else -4.5
            (x, y), yaw = path.pose_at(s, off)
            parts, cl, st = _template(kind, rng)
            out.add(parts, cl, st, float(x), float(y), float(yaw), kind)
        elif u < 0.40:
            for k in range(int(rng.integers(2, 4))):
                (x, y), yaw = path.pose_at(s + 2.2 * k, -4.8)
                parts, cl, st = _template("barrier", rng)
                out.add(parts, cl, st, float(x), float(y), float(yaw), "barrier")
        elif u < 0.50:
            for k in range(int(rng.integers(2, 5))):
                (x, y), yaw = path.pose_at(s + 1.6 * k, -3.9)
                parts, cl, st = _template("cone", rng)
                out.add(parts, cl, st, float(x), float(y), 0.0, "cone")
        elif u < 0.56:
            (x, y), yaw = path.pose_at(s, -5.8)
            parts, cl, st = _template("bicycle", rng)
            out.add(parts, cl, st, float(x), float(y), float(yaw), "bicycle")
        if rng.random() < 0.12:
            for k in range(int(rng.integers(2, 4))):
                (x, y), yaw = path.pose_at(s + 2.2 * k, 4.9)
                kind = "barrier" if rng.random() < 0.7 else "cone"
                parts, cl, st = _template(kind, rng)
                out.add(parts, cl, st, float(x), float(y), float(yaw), kind)
        s += float(rng.uniform(8.0, 12.0))


def _actors(rng: np.random.Generator, path: Path2D, t0_us: int, duration: float, ego_s0: float,
            ego_s_end: float) -> list[Actor]:
    """An oncoming traffic stream (one shared speed, so it never collides with itself), cyclists at the
    left kerb, pedestrians on both sidewalks."""
    L = path.length
    actors: list[Actor] = []

    def add_actor(kind: str, s0: float, offset: float, speed: float, direction: float) -> None:
        parts, cl, st = _template(kind, rng)
        actors.append(Actor(parts, np.asarray(cl, np.int32), np.asarray(st, np.int32), s0, offset, speed, direction,
                            t0_us, kind))

    v_opp = float(rng.uniform(6.0, 11.0))
    s = ego_s0 + 10.0
    while s < L + v_opp * duration:
        u = rng.random()
        kind = "car" if u < 0.68 else "truck" if u < 0.80 else "bus" if u < 0.90 else "motorcycle"
        add_actor(kind, s, 1.75, v_opp, -1.0)
        s += float(rng.uniform(22.0, 55.0))
    s = ego_s0 + 15.0
    while s < min(L, ego_s_end + 80.0):
        add_actor("bicycle", s, 3.6, float(rng.uniform(3.0, 5.0)), -1.0)
        s += float(rng.uniform(40.0, 90.0))
    for side in (-1.0, 1.0):
        s = ego_s0 - 40.0 + float(rng.uniform(0, 5))
        while s < min(L, ego_s_end + 80.0):
            moving = rng.random() < 0.75
            direction = 1.0 if rng.random() < 0.5 else -1.0
            add_actor("pedestrian", s, side * rng.uniform(6.3, 7.5), float(rng.uniform(1.0, 1.6)) * moving, direction)
            s += float(rng.uniform(5.0, 18.0))
    return actors


def make_world(rng: np.random.Generator, origin_xy: tuple[float, float], t0_us: int, n_samples: int) -> SceneWorld:
    """Generate one scene: roads, ground classes, buildings, vegetation, street furniture, actors.

    The ego starts 70 m into the path at `t0_us` and drives for `n_samples` keyframes (0.5 s each).
    The draws from `rng` follow this order (same seed, same world).
    """
    duration = 0.5 * n_samples + 1.0
    ego_s0 = 70.0
    path = make_path(rng, origin_xy, ego_s0 + 12.0 * duration + 130.0)
    ego = make_ego_motion(rng, path, t0_us, duration, ego_s0)
    ground = _make_ground(rng, path, margin=110.0)
    fp = _Footprints(ground)
    static = _StaticBuilder()
    _street_furniture(rng, path, fp, static)
    _buildings_and_walls(rng, path, fp, static)
    _kerb_slots(rng, path, static)
    actors = _actors(rng, path, t0_us, duration, ego_s0, float(ego.s[-1]))
    return SceneWorld(path=path, ego=ego, ground=ground, static=static.primitives(), actors=tuple(actors),
                      static_objects=tuple(static.objects))
