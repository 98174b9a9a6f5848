"""Analytic reference motions and obstacle trajectories shared by the environments.

Everything here is a closed-form function of time returning ``(position, velocity,
acceleration)`` so that the barrier terms can include the exact obstacle acceleration and the
reference feed-forward (paper section VI, Fig. 3).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from afvsgp_gym.validation import check_finite_array, check_real

if TYPE_CHECKING:  # primitives imports this module (sphere_barriers): import it lazily
    from afvsgp_gym.envs.primitives import Primitive


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
#: Time (s) a yielding obstacle takes to come to rest once it stops (see
#: :meth:`ObstacleSpec.stopped_at`): it travels half its speed times this meanwhile.
STOP_DURATION = 0.25


@dataclass(frozen=True)
class ObstacleSpec:
    """An obstacle that rests at ``start``, then moves to ``position`` and stays there.

    The move starts at ``start_time`` (s) and follows the quintic blend with peak speed
    ``speed`` (m/s), so velocity and acceleration are continuous and bounded by
    ``speed`` and ``5.77 * speed**2 / |position - start|``. ``start=None`` means static.

    ``shape`` None (the default) is a sphere of ``radius`` about ``position``. Otherwise it is
    the obstacle's primitive (:mod:`afvsgp_gym.envs.primitives`: a ``Box``, ``Capsule`` or
    ``Plane``) at its final place, whose centre (a plane's ``point``) is ``position``; the
    motion translates it (the orientation stays). ``radius`` is then the radius of the
    smallest ball about ``position`` that holds it (``inf`` for a plane), so code that treats
    every obstacle as a sphere stays conservative; build such a spec with :meth:`of_shape`.
    A plane does not move.

    ``yield_distance`` (m, None for never) makes a moving obstacle yield like a person who
    sees the arm: the Franka env stops it (:meth:`stopped_at`) at the first step where a
    safety sphere comes within this distance of its surface while it moves (the point-mass
    env and the robot bridge's stand-in ignore it). ``stop_time`` (s) is
    when it stopped (``inf``: it has not): from there it follows the same path with a
    speed blended to zero over :data:`STOP_DURATION`, so position, velocity and
    acceleration stay continuous.
    """

    position: np.ndarray
    radius: float
    start: np.ndarray | None = None
    start_time: float = 0.0
    speed: float = 0.2
    shape: Primitive | None = None
    yield_distance: float | None = None
    stop_time: float = math.inf

    def __post_init__(self) -> None:
        if self.yield_distance is not None and not (
                math.isfinite(self.yield_distance) and self.yield_distance > 0):
            raise ValueError(f"yield_distance must be a positive number of metres or None, "
                             f"got {self.yield_distance!r}")
        if self.shape is None:
            return
        from afvsgp_gym.envs import primitives as pr

        if not isinstance(self.shape, pr.Box | pr.Capsule | pr.Plane):
            raise ValueError(f"shape must be a Box, Capsule or Plane (a sphere is shape=None "
                             f"with its radius), got {self.shape!r}")
        anchor = self.shape.point if isinstance(self.shape, pr.Plane) else self.shape.center
        if not np.array_equal(anchor, self.position):
            raise ValueError(f"position {self.position} must be the shape's centre (a plane's "
                             f"point) {anchor}: build it with ObstacleSpec.of_shape")
        if self.radius != bounding_radius(self.shape):
            raise ValueError(f"radius of a {self.kind} must be its bounding radius "
                             f"{bounding_radius(self.shape)}, got {self.radius}: build it "
                             f"with ObstacleSpec.of_shape")
        if isinstance(self.shape, pr.Plane) and self.start is not None:
            raise ValueError("a plane obstacle is static: start must be None")

    @classmethod
    def of_shape(cls, shape: Primitive, start=None, start_time: float = 0.0,
                 speed: float = 0.2, yield_distance: float | None = None) -> ObstacleSpec:
        """The spec of ``shape`` (a primitive at its final place; a ``Sphere`` gives today's
        sphere spec with ``shape=None``) moving from ``start`` like every obstacle."""
        from afvsgp_gym.envs import primitives as pr

        start = None if start is None else np.asarray(start, dtype=np.float64)
        if isinstance(shape, pr.Sphere):
            return cls(np.array(shape.center), shape.radius, start, start_time, speed,
                       yield_distance=yield_distance)
        anchor = shape.point if isinstance(shape, pr.Plane) else getattr(shape, "center", None)
        if anchor is None:
            raise ValueError(f"shape must be a Sphere, Box, Capsule or Plane, got {shape!r}")
        return cls(np.array(anchor), bounding_radius(shape), start, start_time, speed, shape,
                   yield_distance)

    def yields_at(self, t: float) -> bool:
        """Whether the obstacle can still yield at time ``t``: it has a ``yield_distance``,
        has not stopped, and is moving (between the start and the end of its move)."""
        return (self.yield_distance is not None and self.stop_time == math.inf
                and self.start_time < t < self.start_time + self.duration)

    def stopped_at(self, t: float) -> ObstacleSpec:
        """This obstacle stopping from time ``t`` on (the same motion up to ``t``)."""
        return dataclasses.replace(self, stop_time=check_real(t, "t"))

    @property
    def kind(self) -> str:
        """``"sphere"``, ``"box"``, ``"capsule"`` or ``"plane"``."""
        return "sphere" if self.shape is None else type(self.shape).__name__.lower()

    @functools.cached_property
    def primitive(self) -> Primitive:
        """The primitive at ``position`` (a sphere's ``Sphere``)."""
        if self.shape is not None:
            return self.shape
        from afvsgp_gym.envs.primitives import Sphere

        return Sphere(self.position, self.radius)

    def distance(self, offset) -> float:
        """Signed distance (m) to the surface of the point at ``offset`` from the obstacle's
        reference point (its centre, a plane's point, wherever the motion has moved it)."""
        from afvsgp_gym.envs.primitives import point_distance

        return point_distance(self.primitive, offset)

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
        if t <= self.stop_time:
            return self._moving(t)
        # stopping: the path at the warped time sigma, whose rate w = 1 - S(y) falls from
        # 1 to 0 (w' = 0 at the stop: the acceleration is continuous); sigma = ts + T_s
        # (y - int_0^y S), with int_0^y S = y^4 (2.5 - 3 y + y^2)
        ts, span = self.stop_time, STOP_DURATION
        y = min((t - ts) / span, 1.0)
        sigma = ts + span * (y - y ** 4 * (2.5 - 3.0 * y + y * y))
        s, ds, _ = quintic(y)
        w, dw = 1.0 - s, -ds / span
        p, v, a = self._moving(sigma)
        return p, w * v, (w * w) * a + dw * v

    def _moving(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        T = self.duration
        s, ds, dds = quintic((t - self.start_time) / T)
        delta = self.position - self.start
        return self.start + s * delta, (ds / T) * delta, (dds / (T * T)) * delta


def bounding_radius(shape: Primitive) -> float:
    """Radius (m) of the smallest ball about a primitive's centre that holds it (``inf`` for
    a plane)."""
    if hasattr(shape, "half_sizes"):
        return float(np.linalg.norm(shape.half_sizes))
    if hasattr(shape, "half_length"):
        return float(shape.half_length + shape.radius)
    if hasattr(shape, "normal"):
        return math.inf
    return float(shape.radius)


#: The obstacle kinds of ``obstacles=`` entries (``"type"``) and the keys each takes.
OBSTACLE_TYPES = ("sphere", "box", "capsule", "plane")
_MOTION_KEYS = ("start", "start_time", "speed")
OBSTACLE_TYPE_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("type", "position", "radius", *_MOTION_KEYS),
    "box": ("type", "position", "half_sizes", "quat", "rotation", *_MOTION_KEYS),
    "capsule": ("type", "position", "radius", "half_length", "axis", "quat", *_MOTION_KEYS),
    "plane": ("type", "position", "normal"),
}
#: Every key an ``obstacles=`` entry may have (which ones depend on its ``"type"``).
OBSTACLE_KEYS = ("type", "position", "radius", *_MOTION_KEYS, "half_sizes", "quat",
                 "rotation", "half_length", "axis", "normal")
_REQUIRED = {"sphere": ("position", "radius"), "box": ("position", "half_sizes"),
             "capsule": ("position", "radius", "half_length"), "plane": ("position", "normal")}


def quat_to_rotation(quat) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion ``(w, x, y, z)`` (normalised here; MuJoCo's
    convention)."""
    w, x, y, z = np.asarray(quat, dtype=np.float64) / np.linalg.norm(quat)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def parse_obstacles(obstacles: Sequence[Mapping], dim: int, default_start_time: float,
                    types: Sequence[str] = ("sphere",)) -> list:
    """Build ObstacleSpecs from user dicts (or specs, kept); ValueError names the bad key
    (``obstacles[i]['key']``) or value. ``types``: the kinds the env supports (``"type"``,
    default ``"sphere"``; the others need ``dim`` 3, :data:`OBSTACLE_TYPE_KEYS`)."""
    if isinstance(obstacles, Mapping) or not isinstance(obstacles, Sequence) or not obstacles:
        raise ValueError(f"obstacles must be a non-empty list of dicts with keys {OBSTACLE_KEYS}")
    specs = []
    for i, ob in enumerate(obstacles):
        if isinstance(ob, ObstacleSpec):
            if ob.kind not in types:
                raise ValueError(f"obstacles[{i}] is a {ob.kind!r}; valid types: {tuple(types)}")
            specs.append(ob)
            continue
        if not isinstance(ob, Mapping):
            raise ValueError(f"obstacles[{i}] must be a dict with keys {OBSTACLE_KEYS}")
        kind = ob.get("type", "sphere")
        if kind not in types:
            raise ValueError(f"obstacles[{i}]['type'] must be one of {tuple(types)}, got {kind!r}")
        if kind == "plane":
            for key in _MOTION_KEYS:
                if key in ob:
                    raise ValueError(f"obstacles[{i}]['{key}']: a plane is static (no "
                                     f"start, start_time or speed)")
        valid = OBSTACLE_TYPE_KEYS[kind]
        unknown = sorted(set(ob) - set(valid))
        if unknown:
            raise ValueError(f"obstacles[{i}]['{unknown[0]}'] is not a key of a {kind!r} "
                             f"obstacle (unknown keys {unknown}); valid: {valid}")
        for key in _REQUIRED[kind]:
            if key not in ob:
                raise ValueError(f"obstacles[{i}]['{key}'] is missing: a {kind!r} needs "
                                 f"{_REQUIRED[kind]}")
        pos = _obstacle_vector(i, "position", ob["position"], dim)
        start = None if ob.get("start") is None else _obstacle_vector(i, "start", ob["start"],
                                                                      dim)
        speed = _obstacle_positive(i, "speed", ob.get("speed", 0.2))
        t0 = _obstacle_real(i, "start_time", ob.get("start_time", default_start_time))
        if kind == "sphere":
            radius = _obstacle_positive(i, "radius", ob["radius"])
            specs.append(ObstacleSpec(pos, radius, start, t0, speed))
        else:
            specs.append(ObstacleSpec.of_shape(_obstacle_shape(i, kind, ob, pos), start, t0,
                                               speed))
    return specs


def _obstacle_real(i: int, key: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"obstacles[{i}]['{key}'] must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"obstacles[{i}]['{key}'] must be finite, got {out}")
    return out


def _obstacle_positive(i: int, key: str, value) -> float:
    out = _obstacle_real(i, key, value)
    if not out > 0:
        raise ValueError(f"obstacles[{i}]['{key}'] must be > 0, got {out}")
    return out


def _obstacle_vector(i: int, key: str, value, n: int) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"obstacles[{i}]['{key}'] must be finite with shape ({n},), "
                         f"got {value!r}")
    return arr


def _obstacle_shape(i: int, kind: str, ob: Mapping, pos: np.ndarray) -> Primitive:
    """The primitive of a box, capsule or plane entry (ValueError names the key)."""
    from afvsgp_gym.envs import primitives as pr

    if len(pos) != 3:
        raise ValueError(f"obstacles[{i}]['type'] {kind!r} needs 3-D positions")
    rotation, key = None, None
    if "quat" in ob:
        for other in ("rotation", "axis"):
            if other in ob:
                raise ValueError(f"obstacles[{i}]['{other}']: give 'quat' or '{other}', "
                                 f"not both")
        quat = _obstacle_vector(i, "quat", ob["quat"], 4)
        if not np.linalg.norm(quat) > 0:
            raise ValueError(f"obstacles[{i}]['quat'] must be a non-zero (w, x, y, z)")
        rotation, key = quat_to_rotation(quat), "quat"
    elif "rotation" in ob:
        rotation, key = ob["rotation"], "rotation"
    try:
        if kind == "box":
            half = _obstacle_vector(i, "half_sizes", ob["half_sizes"], 3)
            if not np.all(half > 0):
                raise ValueError(f"obstacles[{i}]['half_sizes'] must be > 0, got {half}")
            key = key or "rotation"
            return pr.Box(pos, np.eye(3) if rotation is None else rotation, half)
        if kind == "capsule":
            radius = _obstacle_positive(i, "radius", ob["radius"])
            half_length = _obstacle_positive(i, "half_length", ob["half_length"])
            if rotation is not None:
                axis = rotation[:, 2]  # the local z axis, as MuJoCo's capsules
            else:
                axis = _obstacle_vector(i, "axis", ob.get("axis", (0.0, 0.0, 1.0)), 3)
                key = "axis"
            return pr.Capsule(pos, axis, half_length, radius)
        key = "normal"
        return pr.Plane(pos, _obstacle_vector(i, "normal", ob["normal"], 3))
    except ValueError as exc:
        if str(exc).startswith(f"obstacles[{i}]"):
            raise
        raise ValueError(f"obstacles[{i}]['{key}']: {exc}") from None


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
    return check_finite_array(action, "action", shape)
