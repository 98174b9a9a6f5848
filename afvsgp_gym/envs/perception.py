"""What the filter sees of the world, and what pushes the arm (numpy only, no simulator).

The true state stays the simulator's; the filter sees it through sensors:

- **a camera on the obstacles** (:class:`ObstacleCamera`): the centre of each obstacle is
  sampled at ``t_k = k / obstacle_rate`` (every integer ``k``: the camera runs before the
  episode starts), plus Gaussian noise ``N(0, obstacle_noise^2 I)``, and the sample arrives
  ``obstacle_delay`` seconds later. The *raw* reading at time ``t`` is the newest sample that
  has arrived, its velocity the difference of the last two samples over the period, and its
  acceleration 0 (the plain pipeline; an estimator does better, :mod:`afvsgp_gym.cbf.estimation`);
- **encoders on the joints** (:class:`JointEncoders`): ``q + N(0, position_noise^2)`` and
  ``q' + N(0, velocity_noise^2)``, a fresh draw every control period;
- **pushes** (:class:`Pushes`): starting at rate ``push["rate"]`` per second (a Poisson
  process sampled per control period), each a force of ``push["force"]`` N in a uniform random
  direction for ``push["duration"]`` s, at a random point of a random link (the surface of one
  of its safety spheres), applied through MuJoCo's ``xfrc_applied`` (force and its moment
  about the link's centre of mass).

:func:`pair_covariance` propagates an obstacle estimate's covariance to the covariance of a
(sphere, obstacle) barrier's ``[h, h', lf]`` (first order), the quantities the HOCBF
constraint is built from (eq. 45); :func:`shape_pair_covariance` does the same for a box,
capsule or plane obstacle (or a sphere) from the Hessian of its signed distance.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from afvsgp_gym.validation import check_real

__all__ = ["PUSH_KEYS", "JointEncoders", "ObstacleCamera", "Perception", "Pushes",
           "pair_covariance", "shape_pair_covariance", "shape_pair_gradient"]

#: Keys of the ``push`` option.
PUSH_KEYS = ("force", "duration", "rate")


def _nonnegative(value, name: str) -> float:
    return check_real(value, name, low=0.0)


def _positive(value, name: str) -> float:
    return check_real(value, name, low=0.0, low_open=True)


@dataclass(frozen=True)
class Perception:
    """The sensing and disturbance options of an env (the defaults: exact and undisturbed).

    Parameters
    ----------
    obstacle_noise : float
        Standard deviation (m) of the noise on each obstacle position sample.
    obstacle_rate : float or None
        Camera rate (Hz); None: one sample per control period.
    obstacle_delay : float
        Latency (s) of each sample.
    velocity_noise, position_noise : float
        Standard deviations of the measured ``q'`` (rad/s) and ``q`` (rad).
    push : mapping or None
        ``{"force": N, "duration": s, "rate": pushes per s}`` (every key required).
    """

    obstacle_noise: float = 0.0
    obstacle_rate: float | None = None
    obstacle_delay: float = 0.0
    velocity_noise: float = 0.0
    position_noise: float = 0.0
    push: Mapping | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "obstacle_noise", _nonnegative(self.obstacle_noise, "obstacle_noise"))
        if self.obstacle_rate is not None:
            set_(self, "obstacle_rate", _positive(self.obstacle_rate, "obstacle_rate"))
        set_(self, "obstacle_delay", _nonnegative(self.obstacle_delay, "obstacle_delay"))
        set_(self, "velocity_noise", _nonnegative(self.velocity_noise, "velocity_noise"))
        set_(self, "position_noise", _nonnegative(self.position_noise, "position_noise"))
        if self.push is not None:
            if not isinstance(self.push, Mapping):
                raise ValueError(f"push must be a mapping with keys {list(PUSH_KEYS)} or None. "
                                 f"Got: {self.push!r}")
            unknown = sorted(set(self.push) - set(PUSH_KEYS))
            missing = [k for k in PUSH_KEYS if k not in self.push]
            if unknown or missing:
                raise ValueError(f"push: unknown keys {unknown}, missing keys {missing}; the "
                                 f"keys are {list(PUSH_KEYS)}")
            set_(self, "push", {"force": _nonnegative(self.push["force"], "push['force']"),
                                "duration": _positive(self.push["duration"],
                                                      "push['duration']"),
                                "rate": _nonnegative(self.push["rate"], "push['rate']")})

    @property
    def camera(self) -> bool:
        """The obstacles are seen through the camera (else exactly)."""
        return (self.obstacle_noise > 0 or self.obstacle_rate is not None
                or self.obstacle_delay > 0)

    @property
    def encoders(self) -> bool:
        """The joints are measured with noise (else exactly)."""
        return self.velocity_noise > 0 or self.position_noise > 0

    @property
    def pushes(self) -> bool:
        return self.push is not None and self.push["force"] > 0 and self.push["rate"] > 0

    @property
    def exact(self) -> bool:
        """Nothing configured: today's exact, undisturbed env."""
        return not (self.camera or self.encoders or self.pushes)


class ObstacleCamera:
    """Samples of the obstacle centres at a fixed rate, with noise and latency (module
    docstring). Each sample's noise is a function of the seed and the sample's index, so a
    reading does not depend on when or how often it is asked for."""

    def __init__(self, perception: Perception, control_dt: float, n_obstacles: int):
        rate = perception.obstacle_rate
        self.period = 1.0 / rate if rate is not None else float(control_dt)
        self.noise = perception.obstacle_noise
        self.delay = perception.obstacle_delay
        self.n_obstacles = int(n_obstacles)
        self._seed = 0
        self._cache: dict[int, np.ndarray] = {}

    def reseed(self, seed: int) -> None:
        self._seed = int(seed)
        self._cache.clear()

    def latest_index(self, t: float) -> int:
        """Index ``k`` of the newest sample arrived by time ``t`` (``k / rate + delay <= t``;
        a relative tolerance of 1e-9 periods absorbs the rounding of ``t``)."""
        return math.floor((t - self.delay) / self.period + 1e-9)

    def sample(self, k: int, obstacles) -> np.ndarray:
        """Sample ``k`` (O, 3): the true centres at ``k / rate`` plus its noise."""
        out = self._cache.get(k)
        if out is None:
            t = k * self.period
            out = np.array([ob.state(t)[0] for ob in obstacles], dtype=np.float64)
            if self.noise > 0:
                rng = np.random.default_rng(np.random.SeedSequence([self._seed, k + (1 << 40)]))
                out += self.noise * rng.standard_normal(out.shape)
            if len(self._cache) > 8:
                self._cache.clear()
            self._cache[k] = out
        return out

    def reading(self, t: float, obstacles) -> tuple[np.ndarray, float]:
        """The newest sample (O, 3) arrived by ``t`` and its sample time."""
        k = self.latest_index(t)
        return self.sample(k, obstacles), k * self.period

    def raw_states(self, t: float, obstacles) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The plain pipeline's ``(p, v, a)`` per obstacle: the newest sample, the difference
        of the last two over the period, and 0."""
        k = self.latest_index(t)
        p = self.sample(k, obstacles)
        v = (p - self.sample(k - 1, obstacles)) / self.period
        zero = np.zeros(3)
        return [(p[i].copy(), v[i].copy(), zero) for i in range(len(p))]


class JointEncoders:
    """``q`` and ``q'`` as measured: a fresh Gaussian draw per control period."""

    def __init__(self, perception: Perception):
        self.position_noise = perception.position_noise
        self.velocity_noise = perception.velocity_noise
        self._rng = np.random.default_rng(0)

    def reseed(self, seed: int) -> None:
        self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xE0C]))

    def measure(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        noise = self._rng.standard_normal((2, len(q)))
        return q + self.position_noise * noise[0], qd + self.velocity_noise * noise[1]


class Pushes:
    """Random pushes on the arm's links (module docstring): at most one at a time."""

    def __init__(self, perception: Perception, control_dt: float, bodies: np.ndarray,
                 points: list[np.ndarray]):
        push = perception.push or {"force": 0.0, "duration": 1.0, "rate": 0.0}
        self.force, self.duration = push["force"], push["duration"]
        self.start_probability = -math.expm1(-push["rate"] * control_dt)
        self.bodies = np.asarray(bodies)  # body ids that can be pushed
        self.points = points  # per body: (P, 4) [offset (3) in the body frame, radius]
        self._rng = np.random.default_rng(0)
        self.until = -math.inf
        self.body = -1
        self.wrench_local: tuple[np.ndarray, np.ndarray] | None = None

    def reseed(self, seed: int) -> None:
        self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x9054]))
        self.until, self.body, self.wrench_local = -math.inf, -1, None

    def step(self, t: float) -> bool:
        """Advance to control time ``t``: end a push that has lasted, maybe start one.
        Returns True while a push acts."""
        if t >= self.until:
            self.body, self.wrench_local = -1, None
            if self.force > 0 and self._rng.random() < self.start_probability:
                rng = self._rng
                i = int(rng.integers(len(self.bodies)))
                pts = self.points[i]
                row = pts[int(rng.integers(len(pts)))]
                normal = rng.standard_normal(3)
                normal /= np.linalg.norm(normal)
                direction = rng.standard_normal(3)
                direction /= np.linalg.norm(direction)
                self.body = int(self.bodies[i])
                # the point (body frame) and the force (world frame)
                self.wrench_local = (row[:3] + row[3] * normal, self.force * direction)
                self.until = t + self.duration
        return self.body >= 0

    def apply(self, xfrc_applied: np.ndarray, xpos: np.ndarray, xmat: np.ndarray,
              xipos: np.ndarray) -> None:
        """Write the acting push (if any) into ``xfrc_applied`` (every other row zero)."""
        xfrc_applied[:] = 0.0
        if self.body < 0 or self.wrench_local is None:
            return
        b = self.body
        point_local, force = self.wrench_local
        point = xpos[b] + xmat[b].reshape(3, 3) @ point_local
        xfrc_applied[b, :3] = force
        xfrc_applied[b, 3:] = np.cross(point - xipos[b], force)


def pair_covariance(n: np.ndarray, distance: np.ndarray, v_rel: np.ndarray,
                    state_cov: np.ndarray, relative_acc: np.ndarray | None = None) -> np.ndarray:
    """Covariance (K, 3, 3) of ``[h, h', lf]`` of K (sphere, obstacle) barriers from the
    per-axis covariance ``state_cov`` (K, 3, 3) of the obstacle's ``[p, v, a]`` (the same for
    x, y and z; a constant-velocity estimate has a zero ``a`` row), to first order.

    With ``d = p_s - p_o``, ``n = d / |d|``, ``P = I - n n'``, ``v = v_s - v_o`` and ``w =
    a_s - a_o`` (``relative_acc`` (K, 3): the model's sphere acceleration at zero action minus
    the obstacle's): ``h = |d| - r``, ``h' = n'v``, and ``lf = n'w + |P v|^2 / |d|`` (the
    curvature), so ``dh/dp_o = -n``; ``dh'/dp_o = -P v / |d|``, ``dh'/dv_o = -n``; ``dlf/dv_o
    = -2 P v / |d|``, ``dlf/da_o = -n``, ``dlf/dp_o = (2 (n'v) P v + |P v|^2 n) / |d|^2 - P w /
    |d|``. ``relative_acc`` None: a model whose ``lf`` is 0 whatever the obstacles (nothing
    known), so ``lf``'s row is 0."""
    k = len(distance)
    inv = 1.0 / distance
    nv = np.einsum("ki,ki->k", n, v_rel)
    pv = v_rel - nv[:, None] * n
    pv2 = np.einsum("ki,ki->k", pv, pv)
    grad = np.zeros((k, 3, 3, 3))  # (pair, [h, h', lf], [p, v, a], xyz)
    grad[:, 0, 0] = -n
    grad[:, 1, 0] = -pv * inv[:, None]
    grad[:, 1, 1] = -n
    if relative_acc is not None:
        pw = relative_acc - np.einsum("ki,ki->k", n, relative_acc)[:, None] * n
        grad[:, 2, 0] = ((2.0 * nv[:, None] * pv + pv2[:, None] * n) * inv[:, None]
                         - pw) * inv[:, None]
        grad[:, 2, 1] = -2.0 * pv * inv[:, None]
        grad[:, 2, 2] = -n
    return np.einsum("kab,kiax,kjbx->kij", state_cov, grad, grad)


def shape_pair_gradient(n: np.ndarray, hessian: np.ndarray, v_rel: np.ndarray,
                        relative_acc: np.ndarray | None = None) -> np.ndarray:
    """``d [h, h', lf] / d [c, c', c'']`` (K, 3, 3, 3: pair, ``[h, h', lf]``, ``[p, v, a]``,
    xyz) of K (sphere, obstacle) barriers with respect to the obstacle's reference point
    ``c`` and its motion, for any primitive of :mod:`~afvsgp_gym.envs.primitives` from the
    closest feature's normal ``n`` and the Hessian ``H`` (K, 3, 3) of the signed distance
    (:func:`~afvsgp_gym.envs.primitives.pair_hessians`).

    With ``p = p_s - c``, ``v = v_s - c'`` and ``w = a_s - c''`` (``relative_acc``, None: a
    model whose ``lf`` is 0, its row 0): ``h = d(p) - r``, ``h' = n'v``, ``lf = n'w + v'H v``.
    In every region of every primitive ``d`` is, up to a constant, the distance ``rho`` to an
    affine feature (a point, a line, a plane: a sphere's or a cap's centre, the capsule's
    axis, a box's corner, edge or face, a plane), so ``grad d = n``, ``grad n = H = (Q - n n')
    / rho`` with ``Q`` the projector onto the feature's normal space, and ``grad (v'H v) =
    -(2 (n'v) H v + (v'H v) n) / rho``; ``H``'s nonzero eigenvalues are all ``1 / rho``, so
    ``1 / rho = |H|_F^2 / tr H`` (where ``H = 0``, faces and planes, the term is 0). Then
    ``dh/dc = -n``; ``dh'/dc = -H v``, ``dh'/dc' = -n``; ``dlf/dc = (2 (n'v) H v + (v'H v)
    n) / rho - H w``, ``dlf/dc' = -2 H v``, ``dlf/dc'' = -n``: for a sphere (``H = P /
    |d|``) :func:`pair_covariance`'s gradient. Within a region; where regions meet ``H``
    jumps and the first order holds on either side."""
    k = len(n)
    hv = np.einsum("kij,kj->ki", hessian, v_rel)
    grad = np.zeros((k, 3, 3, 3))
    grad[:, 0, 0] = -n
    grad[:, 1, 0] = -hv
    grad[:, 1, 1] = -n
    if relative_acc is not None:
        nv = np.einsum("ki,ki->k", n, v_rel)
        vhv = np.einsum("ki,ki->k", v_rel, hv)
        trace = np.einsum("kii->k", hessian)
        frob = np.einsum("kij,kij->k", hessian, hessian)
        inv_rho = np.divide(frob, trace, out=np.zeros(k), where=trace > 0.0)
        hw = np.einsum("kij,kj->ki", hessian, relative_acc)
        grad[:, 2, 0] = (2.0 * nv[:, None] * hv + vhv[:, None] * n) * inv_rho[:, None] - hw
        grad[:, 2, 1] = -2.0 * hv
        grad[:, 2, 2] = -n
    return grad


def shape_pair_covariance(n: np.ndarray, hessian: np.ndarray, v_rel: np.ndarray,
                          state_cov: np.ndarray,
                          relative_acc: np.ndarray | None = None) -> np.ndarray:
    """:func:`pair_covariance` for an obstacle of any primitive: the covariance (K, 3, 3) of
    ``[h, h', lf]`` from the per-axis covariance ``state_cov`` (K, 3, 3) of the obstacle's
    ``[c, c', c'']`` (its reference point: a centre, a plane's point), to first order through
    :func:`shape_pair_gradient`. The mean of ``lf``'s error to second order is ``tr(H) sigma_v^2``
    (the curvature ``v'H v`` is convex in the obstacle's velocity: ``2 sigma_v^2 / |d|`` for a
    sphere, ``sigma_v^2 / rho`` beside a capsule or at a box's edge, 0 on a face or plane)."""
    grad = shape_pair_gradient(n, hessian, v_rel, relative_acc)
    # sum over the axes x of G_x Sigma G_x', G_x = grad[k, :, :, x]: batched 3 x 3 products
    per_axis = grad.transpose(0, 3, 1, 2)  # (pair, xyz, [h, h', lf], [p, v, a])
    left = np.matmul(per_axis, state_cov[:, None])
    return np.matmul(left, per_axis.transpose(0, 1, 3, 2)).sum(axis=1)
