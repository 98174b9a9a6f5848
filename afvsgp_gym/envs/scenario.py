"""Analytic reference motions and obstacle trajectories shared by the environments.

Everything here is a closed-form function of time returning ``(position, velocity,
acceleration)`` so that the barrier terms can include the exact obstacle acceleration and the
reference feed-forward (paper section VI, Fig. 3).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


def quintic(tau: float) -> tuple[float, float, float]:
    """Minimum-jerk blend S(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 clamped to [0, 1].

    Returns ``(S, dS/dtau, d2S/dtau2)``; S' and S'' vanish at both ends.
    """
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = tau * tau
    s = t2 * tau * (10.0 - 15.0 * tau + 6.0 * t2)
    ds = 30.0 * t2 * (1.0 - tau) ** 2
    dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau)
    return s, ds, dds


#: Peak of dS/dtau for the quintic blend (at tau = 1/2).
QUINTIC_PEAK_SLOPE = 1.875


@dataclass(frozen=True)
class ObstacleSpec:
    """A sphere that rests at ``start``, then moves to ``position`` and stays there.

    The move starts at ``start_time`` (s) and follows the quintic blend with peak speed
    ``speed`` (m/s), so velocity and acceleration are continuous and bounded by
    ``speed`` and ``5.77 * speed**2 / |position - start|``. ``start=None`` means static.
    """

    position: np.ndarray
    radius: float
    start: np.ndarray | None = None
    start_time: float = 0.0
    speed: float = 0.2

    @functools.cached_property
    def duration(self) -> float:
        """Length of the move (s); 0 for a static obstacle."""
        if self.start is None:
            return 0.0
        dist = float(np.linalg.norm(self.position - self.start))
        return QUINTIC_PEAK_SLOPE * dist / self.speed if dist > 0 else 0.0

    @functools.cached_property
    def _rest(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        zero = np.zeros(self.position.shape)
        out = (self.position.copy(), zero, zero.copy())
        for arr in out:
            arr.flags.writeable = False
        return out

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Obstacle centre position, velocity and acceleration at time ``t`` (read-only when
        static)."""
        T = self.duration
        if T == 0.0:
            return self._rest
        s, ds, dds = quintic((t - self.start_time) / T)
        delta = self.position - self.start
        return self.start + s * delta, (ds / T) * delta, (dds / (T * T)) * delta


OBSTACLE_KEYS = ("position", "radius", "start", "start_time", "speed")


def parse_obstacles(obstacles: Sequence[Mapping], dim: int, default_start_time: float) -> list:
    """Build ObstacleSpecs from user dicts; ValueError names the bad key or value."""
    if isinstance(obstacles, Mapping) or not isinstance(obstacles, Sequence) or not obstacles:
        raise ValueError(f"obstacles must be a non-empty list of dicts with keys {OBSTACLE_KEYS}")
    specs = []
    for i, ob in enumerate(obstacles):
        if isinstance(ob, ObstacleSpec):
            specs.append(ob)
            continue
        if not isinstance(ob, Mapping):
            raise ValueError(f"obstacles[{i}] must be a dict with keys {OBSTACLE_KEYS}")
        unknown = set(ob) - set(OBSTACLE_KEYS)
        if unknown:
            raise ValueError(
                f"obstacles[{i}] has unknown keys {sorted(unknown)}; valid: {OBSTACLE_KEYS}"
            )
        if "position" not in ob or "radius" not in ob:
            raise ValueError(f"obstacles[{i}] needs 'position' and 'radius'")
        pos = np.asarray(ob["position"], dtype=np.float64)
        start = None if ob.get("start") is None else np.asarray(ob["start"], dtype=np.float64)
        for name, arr in (("position", pos), ("start", start)):
            if arr is not None and (arr.shape != (dim,) or not np.all(np.isfinite(arr))):
                raise ValueError(f"obstacles[{i}]['{name}'] must be finite with shape ({dim},)")
        radius = float(ob["radius"])
        speed = float(ob.get("speed", 0.2))
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"obstacles[{i}]['radius'] must be > 0, got {radius}")
        if not (np.isfinite(speed) and speed > 0):
            raise ValueError(f"obstacles[{i}]['speed'] must be > 0, got {speed}")
        t0 = float(ob.get("start_time", default_start_time))
        specs.append(ObstacleSpec(pos, radius, start, t0, speed))
    return specs


@dataclass(frozen=True)
class CyclicReference:
    """Cyclic reference ``r(t) = c + a(t) sin(2 pi t / period) w(t)`` (paper Fig. 3).

    ``a(t)`` grows from ``warmup_amplitude`` to ``amplitude`` over
    ``[ramp_start, ramp_start + ramp_duration]`` (so the motion stays small and away from the
    obstacles during warm-up); the motion direction ``w(t)`` turns from ``axis1`` ("y") to
    ``axis2`` ("z") over ``[switch_time, switch_time + switch_duration]`` (unseen data).
    All blends are quintic, so r, r' and r'' are continuous.
    """

    center: np.ndarray
    axis1: np.ndarray
    axis2: np.ndarray
    amplitude: float
    warmup_amplitude: float
    period: float
    ramp_start: float
    ramp_duration: float = 1.0
    switch_time: float = np.inf
    switch_duration: float = 0.5

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reference position, velocity and acceleration at time ``t``."""
        # amplitude a(t)
        b, db, ddb = quintic((t - self.ramp_start) / self.ramp_duration)
        span = self.amplitude - self.warmup_amplitude
        a = self.warmup_amplitude + span * b
        da = span * db / self.ramp_duration
        dda = span * ddb / self.ramp_duration**2
        # oscillation s(t)
        w0 = 2.0 * math.pi / self.period
        sw, cw = math.sin(w0 * t), math.cos(w0 * t)
        s, ds, dds = sw, w0 * cw, -(w0**2) * sw
        # direction w(t) = cos(th) e1 + sin(th) e2, th = pi/2 S((t - ts) / Tb)
        if math.isfinite(self.switch_time):
            q, dq, ddq = quintic((t - self.switch_time) / self.switch_duration)
        else:
            q, dq, ddq = 0.0, 0.0, 0.0
        f0 = a * s
        f1 = da * s + a * ds
        f2 = dda * s + 2 * da * ds + a * dds
        if dq == 0.0 and ddq == 0.0 and q in (0.0, 1.0):  # fixed direction: fast path
            e = self.axis1 if q == 0.0 else self.axis2
            return self.center + f0 * e, f1 * e, f2 * e
        k = 0.5 * math.pi
        th, dth = k * q, k * dq / self.switch_duration
        ddth = k * ddq / self.switch_duration**2
        ct, st = math.cos(th), math.sin(th)
        e_r = ct * self.axis1 + st * self.axis2
        e_t = ct * self.axis2 - st * self.axis1
        # r = c + a s w, w' = th' e_t, w'' = th'' e_t - th'^2 e_r
        pos = self.center + f0 * e_r
        vel = f1 * e_r + (f0 * dth) * e_t
        acc = (f2 - f0 * dth * dth) * e_r + (2 * f1 * dth + f0 * ddth) * e_t
        return pos, vel, acc


def sphere_barriers(
    d: np.ndarray, v_rel: np.ndarray, radius: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kinematic part of ``h = |d| - radius`` for K sphere pairs at once.

    ``d`` (K, n) = centre minus obstacle centre, ``v_rel`` (K, n) its time derivative,
    ``radius`` (K,) the sum of the two radii. Returns ``(h, h', n, curvature)`` with
    ``n = d/|d|`` and ``h'' = n . (a - a_obs) + curvature``,
    ``curvature = (|v_rel|^2 - (n . v_rel)^2) / |d|``.
    """
    dist = np.maximum(np.sqrt(np.einsum("ki,ki->k", d, d)), 1e-9)
    n = d / dist[:, None]
    ndv = np.einsum("ki,ki->k", n, v_rel)
    curv = (np.einsum("ki,ki->k", v_rel, v_rel) - ndv * ndv) / dist
    return dist - radius, ndv, n, curv


def dot3(a, b) -> float:
    """``a . b`` of two 3-sequences of floats, summed as ``(a0 b0 + a2 b2) + a1 b1``: the order
    in which numpy's ``einsum`` reduces three terms on two-lane (128-bit SIMD) builds, the x86-64
    wheels, so :func:`sphere_barrier` gives the numbers of :func:`sphere_barriers` bit for bit
    there (on other builds they agree to rounding)."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def sphere_barrier(
    d: Sequence[float], v_rel: Sequence[float], radius: float
) -> tuple[float, float, list[float], float]:
    """:func:`sphere_barriers` for one pair in Python floats (no per-call numpy cost):
    ``(h, h', n, curvature)`` with ``n`` a list."""
    dist = max(math.sqrt(dot3(d, d)), 1e-9)
    n = [x / dist for x in d]
    ndv = dot3(n, v_rel)
    curv = (dot3(v_rel, v_rel) - ndv * ndv) / dist
    return dist - radius, ndv, n, curv


def check_action(action, shape: tuple[int, ...]) -> np.ndarray:
    """float64 copy of ``action``; ValueError on wrong shape or non-finite entries."""
    try:
        a = np.array(action, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"action must be numeric with shape {shape}: {exc}") from None
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"action must be finite (no NaN/inf), got {a}")
    return a
