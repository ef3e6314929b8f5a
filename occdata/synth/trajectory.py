"""Road centre-line paths and motion along them (ego and actors), in the global frame.

A path is a dense polyline sampled every `PATH_STEP` metres of arc length; everything that moves
(the ego car, other cars, pedestrians, cyclists) is a point at arc length `s(t)` plus a lateral
offset to the left of the path, heading along (or against) the path tangent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "PATH_STEP",
    "EgoMotion",
    "Path2D",
    "make_ego_motion",
    "make_path",
]

PATH_STEP = 0.25  # m between path samples
LANE_OFFSET_EGO = -1.75  # ego drives in the right-hand lane (y left, so right is negative)


@dataclass(frozen=True, eq=False)
class Path2D:
    """A dense polyline: `xy (N, 2) float64` global metres, `yaw (N,) float64` tangent heading (rad),
    `s (N,) float64` arc length; plus `extra_roads`: other centre lines (side roads at intersections),
    a tuple of `(M, 2) float64` polylines."""

    xy: np.ndarray
    yaw: np.ndarray
    s: np.ndarray
    curvature: np.ndarray
    extra_roads: tuple[np.ndarray, ...]

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def pose_at(self, s: np.ndarray | float, offset: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Position `(..., 2)` and heading `(...)` at arc length `s` with a lateral offset (left +)."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        # Unwrapped yaw interpolates smoothly through +-pi.
        yaw = np.interp(s, self.s, self.yaw)
        off = np.asarray(offset, dtype=np.float64)
        x = x - np.sin(yaw) * off
        y = y + np.cos(yaw) * off
        return np.stack([x, y], axis=-1), yaw


def make_path(rng: np.random.Generator, origin_xy: tuple[float, float], length: float) -> Path2D:
    """A random road path of at least `length` metres: straights, 90 degree turns (radius 15-25 m),
    and straight crossings; side roads are added at every turn and crossing (intersections)."""
    x, y = origin_xy
    yaw = float(rng.uniform(-np.pi, np.pi))
    pts: list[tuple[float, float, float]] = [(x, y, yaw)]
    extra: list[np.ndarray] = []
    total = 0.0
    first = True
    # Net turn in quarter turns; kept within [-1, 1] so the path never loops back onto itself.
    heading_q = 0
    while total < length:
        seg = float(rng.uniform(90.0, 130.0)) if first else float(rng.uniform(35.0, 80.0))
        first = False
        n = max(int(seg / PATH_STEP), 1)
        for _ in range(n):
            x += PATH_STEP * np.cos(yaw)
            y += PATH_STEP * np.sin(yaw)
            pts.append((x, y, yaw))
        total += n * PATH_STEP
        if total >= length:
            break
        want_turn = rng.random() < 0.6
        sign = 1.0 if rng.random() < 0.5 else -1.0
        if abs(heading_q + sign) > 1:
            sign = -sign
        if want_turn:  # turn at an intersection
            heading_q += int(sign)
            radius = float(rng.uniform(15.0, 25.0))
            # The road we leave continues straight through the intersection.
            ahead = np.array([[x, y], [x + (radius + 45.0) * np.cos(yaw), y + (radius + 45.0) * np.sin(yaw)]])
            extra.append(ahead)
            n_arc = max(int(radius * np.pi / 2 / PATH_STEP), 1)
            dyaw = sign * (np.pi / 2) / n_arc
            step = radius * abs(dyaw)
            for _ in range(n_arc):
                yaw += dyaw / 2
                x += step * np.cos(yaw)
                y += step * np.sin(yaw)
                yaw += dyaw / 2
                pts.append((x, y, yaw))
            total += n_arc * step
            # The road we join also extends back across the intersection.
            back = np.array([[x, y], [x - (radius + 45.0) * np.cos(yaw), y - (radius + 45.0) * np.sin(yaw)]])
            extra.append(back)
        else:  # straight crossing
            nx, ny = -np.sin(yaw), np.cos(yaw)
            extra.append(np.array([[x - 70.0 * nx, y - 70.0 * ny], [x + 70.0 * nx, y + 70.0 * ny]]))
    arr = np.asarray(pts, dtype=np.float64)
    xy = arr[:, :2]
    yaws = arr[:, 2]
    seglen = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seglen)])
    curv = np.zeros_like(s)
    curv[1:] = np.abs(np.diff(yaws)) / np.maximum(seglen, 1e-9)
    return Path2D(xy=xy, yaw=yaws, s=s, curvature=curv, extra_roads=tuple(extra))


@dataclass(frozen=True, eq=False)
class EgoMotion:
    """Ego arc length on the path as a function of time: `t_us (T,) int64` microseconds,
    `s (T,) float64` metres (dense, 10 ms steps; interpolate between)."""

    path: Path2D
    t_us: np.ndarray
    s: np.ndarray

    def s_at(self, t_us: np.ndarray | int) -> np.ndarray:
        return np.interp(np.asarray(t_us, dtype=np.float64), self.t_us.astype(np.float64), self.s)

    def pose_at(self, t_us: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Ego position `(..., 2)` (ground, z = 0) and yaw at timestamp(s) `t_us`."""
        return self.path.pose_at(self.s_at(t_us), LANE_OFFSET_EGO)

    def speed_at(self, t_us: np.ndarray | int) -> np.ndarray:
        dt = 10_000
        return (self.s_at(np.asarray(t_us) + dt) - self.s_at(np.asarray(t_us) - dt)) / (2 * dt * 1e-6)


def make_ego_motion(
    rng: np.random.Generator, path: Path2D, t0_us: int, duration_s: float, s0: float
) -> EgoMotion:
    """Integrate a smooth speed profile (5-12 m/s) that slows for curves (lateral acc <= 3 m/s^2)."""
    dt = 0.01
    n = int(np.ceil(duration_s / dt)) + 2
    v_base = rng.uniform(7.0, 10.5)
    amp = rng.uniform(0.5, 2.0)
    omega = rng.uniform(0.15, 0.4)
    phase = rng.uniform(0, 2 * np.pi)
    # Curvature look-ahead: the speed cap depends on the tightest curve within 20 m ahead.
    win = int(20.0 / PATH_STEP)
    curv = path.curvature
    padded = np.concatenate([curv, np.zeros(win)])
    ahead = np.lib.stride_tricks.sliding_window_view(padded, win + 1).max(axis=1)[: len(curv)]
    s = np.empty(n)
    s[0] = s0
    v_prev = v_base
    for i in range(1, n):
        t = (i - 1) * dt
        v_want = v_base + amp * np.sin(omega * t + phase)
        k = ahead[min(int(s[i - 1] / PATH_STEP), len(ahead) - 1)]
        v_cap = np.sqrt(3.0 / max(k, 1e-6))
        v_target = float(np.clip(min(v_want, v_cap), 5.0, 12.0))
        # Limit acceleration to +-2.5 m/s^2 for a realistic speed trace.
        v = float(np.clip(v_target, v_prev - 2.5 * dt, v_prev + 2.5 * dt))
        s[i] = s[i - 1] + v * dt
        v_prev = v
    t_us = t0_us + np.round(np.arange(n) * dt * 1e6).astype(np.int64)
    return EgoMotion(path=path, t_us=t_us, s=s)
