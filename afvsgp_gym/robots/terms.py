"""The barrier terms of a torque-controlled Franka arm from the robot's own model (numpy only).

The robot compensates gravity itself (libfranka's torque interface adds it), so the
commanded torque ``tau`` obeys ``M(q) q'' + c(q, q') = tau + tau_res``, with ``M`` and ``c =
C(q, q') q'`` from the robot's model (libfranka ``Model.mass``, ``Model.coriolis``) and
``tau_res`` what that model misses (a payload, friction, the model's errors): the learner's
job. The joint acceleration at zero action is ``q''_0 = -M^-1 c`` and its gain
``M^-1 diag(action_scale)``.

The barriers and their conventions are :class:`~afvsgp_gym.envs.franka.FrankaObstacleEnv`'s
(paper eqs. 44-46), so the same :class:`~afvsgp_gym.cbf.SafetyController` options apply:

- every (sphere ``s``, obstacle ``o``) pair, obstacle-major: ``h = |d| - (r_s + r_o)``,
  ``d = p_s - p_o``, ``h' = n.v_rel`` (``n = d/|d|``, ``v_rel = v_s - v_o``), relative
  degree 2, ``lf = n.(J_s q''_0 + J_s' q' - a_o) + (|v_rel|^2 - (n.v_rel)^2)/|d|`` and
  ``lg = n' J_s M^-1 diag(action_scale)``; features ``xi = [q, q', d, v_rel]``;
- with ``self_collision`` (:class:`~afvsgp_gym.envs.self_collision.SelfCollisionPairs`,
  :func:`panda_self_collision_pairs` for the Panda's arm spheres), one barrier per pair of
  spheres on non-adjacent links and the base: the pair's barrier with the second sphere in
  the obstacle's place (``h = |p_a - p_b| - r_a - r_b``, the same ``lf`` and ``lg`` with
  ``J_a - J_b``, features ``[q, q', p_a - p_b, v_a - v_b]``), as the simulation's
  ``self_collision`` (on by default there);
- then the 28 joint range and speed barriers of
  :class:`~afvsgp_gym.envs.joint_limits.JointLimits` with ``lf, lg = +-(q''_0, M^-1
  diag(action_scale))`` of their joint and features ``[q, q', 0 (6)]``.

**Boxes, capsules and planes** (``shapes``): an obstacle may be any primitive of
:mod:`~afvsgp_gym.envs.primitives` (``Box``, ``Capsule``, ``Plane``; a ``Sphere`` is the
sphere above), translated with the estimate's position, velocity and acceleration (its
orientation fixed; ``p_o`` is its reference point: a centre, a plane's point). Its pairs'
``h = d(p_s - p_o) - r_s`` with ``d`` the exact signed distance, ``n`` the closest feature's
normal and the curvature ``v_rel' H v_rel`` come from
:func:`~afvsgp_gym.envs.primitives.pair_barriers`, and ``xi`` holds ``n (h + r_s)`` (the
sphere centre's offset from the closest surface point) in place of ``d``: the simulation's
terms for the same obstacles. A scene of spheres only takes the sphere formulas above, bit
for bit as before.

An obstacle estimate with a covariance (:class:`ObstacleEstimate`, the perception issue's
per-axis covariance of ``[p, v, a]``) gives each pair's covariance of ``[h, h', lf]`` and
lowers ``lf`` by the mean of its error (the curvature is convex in the obstacle's velocity),
as the simulation does for spheres: for spheres only
:func:`~afvsgp_gym.envs.perception.pair_covariance` and ``2 sigma_v^2 / |d|``; with a box,
capsule or plane in the scene :func:`~afvsgp_gym.envs.perception.shape_pair_covariance` for
every pair (first order through the signed distance's gradient ``n`` and Hessian ``H``,
:func:`~afvsgp_gym.envs.primitives.pair_barriers_and_hessians`) and ``tr(H) sigma_v^2`` (0
on a face or a plane). The joint-limit rows' covariance is 0 (the encoders are taken as
exact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afvsgp_gym import _compiled
from afvsgp_gym.envs.joint_limits import (
    FRANKA_MAX_ACCELERATION,
    JointLimits,
    arm_layout,
    joint_projection,
    limit_calibration,
)
from afvsgp_gym.envs.perception import pair_covariance, shape_pair_covariance
from afvsgp_gym.envs.primitives import (
    Box,
    Capsule,
    Plane,
    Sphere,
    hessian_stack,
    pair_barriers,
    pair_barriers_and_hessians,
    stack_shapes,
)
from afvsgp_gym.envs.safety_spheres import PANDA_BASE_SPHERES
from afvsgp_gym.envs.scenario import bounding_radius, sphere_barriers
from afvsgp_gym.envs.self_collision import PANDA_SELF_COLLISION_SPHERES, SelfCollisionPairs
from afvsgp_gym.robots.kinematics import SphereKinematics
from afvsgp_gym.types import BarrierLayout, BarrierSet

_arm = _compiled.extension("arm")

__all__ = ["FEATURE_DIM", "BarrierModel", "ObstacleEstimate", "panda_self_collision_pairs"]

#: Features per barrier: ``[q (7), q' (7), d (3), v_rel (3)]``, the simulation's.
FEATURE_DIM = 20


def _rows(value, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}. Got: {arr.shape}")
    return arr


@dataclass(frozen=True)
class ObstacleEstimate:
    """What perception says about ``O`` obstacles at the control time.

    Attributes
    ----------
    position, velocity, acceleration : ndarray of shape (O, 3)
        Reference points (m: a sphere's, box's or capsule's centre, a plane's point),
        velocities (m/s), accelerations (m/s^2) in the robot's base frame.
    covariance : ndarray of shape (O, 3, 3) or None
        Per-axis covariance of ``[p, v, a]`` (the same for x, y and z, as
        :class:`~afvsgp_gym.cbf.estimation.ObstacleEstimator` gives it); None: exact.
    """

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        pos = np.asarray(self.position, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"position must have shape (O, 3). Got: {pos.shape}")
        o = pos.shape[0]
        object.__setattr__(self, "position", pos)
        for name in ("velocity", "acceleration"):
            object.__setattr__(self, name, _rows(getattr(self, name), (o, 3), name))
        if self.covariance is not None:
            object.__setattr__(self, "covariance",
                               _rows(self.covariance, (o, 3, 3), "covariance"))


class BarrierModel:
    """Every barrier's :class:`~afvsgp_gym.types.BarrierSet` at a measured state, from the
    robot's mass matrix and Coriolis vector (module docstring).

    Parameters
    ----------
    kinematics : SphereKinematics
        The safety spheres' kinematics (``S`` spheres).
    sphere_radii : array_like of shape (S,)
        m, > 0.
    obstacle_radii : array_like of shape (O,)
        m, > 0: a sphere's radius; a shaped obstacle's bounding radius
        (:attr:`~afvsgp_gym.envs.scenario.ObstacleSpec.radius`, ``inf`` for a plane).
    limits : JointLimits or None
        The joint range and speed barriers (and their margins); None: obstacle pairs only.
    action_scale : float or array_like of shape (7,)
        Nm per action unit (1: the action is the torque).
    torque_error : float or array_like of shape (7,)
        A bound ``tau_bar`` (Nm, per joint) on the torque the model misses (``|tau_res_j|
        <= tau_bar_j``: an undeclared payload's weight, friction): every barrier's ``lf`` is
        lowered by the most it can change ``h^(r)``, ``sum_j |lg_j| tau_bar_j /
        action_scale_j``, so the filter holds for every such residual (the simulation's
        ``"true_robust"`` terms do the same for friction). 0 (default): the model is taken
        as exact.
    shapes : sequence of O (Box, Capsule, Plane, Sphere or None) or None
        Each obstacle's primitive (:mod:`~afvsgp_gym.envs.primitives`; its size and
        orientation: the estimate's position places it, the primitive's own centre or point
        is not used), None for a sphere of its ``obstacle_radii`` entry
        (:attr:`~afvsgp_gym.envs.scenario.ObstacleSpec.shape`). None (default): every
        obstacle a sphere.
    self_collision : SelfCollisionPairs or None
        Pairs of the kinematics' spheres (and fixed spheres at centres in the base frame)
        kept apart, after the obstacle pairs (:func:`panda_self_collision_pairs`: the
        simulation's 93 for the Panda's arm spheres). None (default): none.
    backend : {"auto", "numpy", "compiled"}
        The sphere pairs' arithmetic (:mod:`afvsgp_gym._compiled`, the extension ``"arm"``)
        in a scene of spheres without an obstacle covariance; the numpy path (the reference,
        equal to rounding) runs otherwise.
    """

    #: The filter settings :class:`~afvsgp_gym.envs.franka.FrankaObstacleEnv` suggests
    #: (:attr:`filter_defaults`; tests/robots hold them equal).
    OBSTACLE_ACTIVATION, RANGE_ACTIVATION, SPEED_ACTIVATION = 0.15, 0.3, float("inf")
    OBSTACLE_DECELERATION = 5.0
    SPEED_GAIN = 25.0

    def __init__(self, kinematics: SphereKinematics, sphere_radii, obstacle_radii,
                 limits: JointLimits | None, action_scale=1.0, torque_error=0.0, *,
                 shapes=None, self_collision: SelfCollisionPairs | None = None,
                 backend: str | _compiled.Backend = "auto") -> None:
        if not isinstance(kinematics, SphereKinematics):
            raise ValueError(f"kinematics must be a SphereKinematics. Got: {kinematics!r}")
        n_s = len(kinematics.links)
        rs = np.asarray(sphere_radii, dtype=np.float64)
        ro = np.atleast_1d(np.asarray(obstacle_radii, dtype=np.float64))
        if rs.shape != (n_s,) or not np.all(rs > 0):
            raise ValueError(f"sphere_radii must be {n_s} numbers > 0. Got: {sphere_radii!r}")
        if ro.ndim != 1 or not np.all(ro > 0):
            raise ValueError(f"obstacle_radii must be numbers > 0. Got: {obstacle_radii!r}")
        if limits is not None and not isinstance(limits, JointLimits):
            raise ValueError(f"limits must be a JointLimits or None. Got: {limits!r}")
        scale = np.broadcast_to(np.asarray(action_scale, dtype=np.float64), (7,)).copy()
        if not np.all(np.isfinite(scale) & (scale > 0)):
            raise ValueError(f"action_scale must be > 0. Got: {action_scale!r}")
        err = np.broadcast_to(np.asarray(torque_error, dtype=np.float64), (7,)).copy()
        if not np.all(np.isfinite(err) & (err >= 0)):
            raise ValueError(f"torque_error must be >= 0. Got: {torque_error!r}")
        self.torque_error = err
        self._error_per_action = err / scale
        self.kinematics = kinematics
        self.sphere_radii, self.obstacle_radii = rs, ro
        self.limits = limits
        self.action_scale = scale
        self.n_spheres, self.n_obstacles = n_s, len(ro)
        self.n_pairs = n_s * len(ro)
        self._radius = (ro[:, None] + rs[None, :]).ravel()
        self.shapes = _check_shapes(shapes, ro)
        self._shape_const = None
        if any(shape is not None for shape in self.shapes):  # pair_barriers' stacks
            prims = [Sphere(np.zeros(3), r) if shape is None else shape
                     for shape, r in zip(self.shapes, ro, strict=True)]
            self._shape_const = (stack_shapes(prims, n_s), hessian_stack(prims, n_s),
                                 np.tile(rs, len(ro)),
                                 np.repeat([shape is None for shape in self.shapes], n_s))
        if self_collision is not None and (not isinstance(self_collision, SelfCollisionPairs)
                                           or self_collision.n_moving != n_s):
            raise ValueError(f"self_collision must be the SelfCollisionPairs of the {n_s} "
                             f"spheres or None. Got: {self_collision!r}")
        self.self_collision = self_collision
        #: the rows of sphere pairs (obstacle, then self-collision), before the limits
        self.n_pair_rows = self.n_pairs + (0 if self_collision is None else len(self_collision))
        self.n_barriers = self.n_pair_rows + (0 if limits is None else limits.n_barriers)
        self.backend = _compiled.resolve(backend, ("arm",))
        self._pair_index = self._pair_table() if self.backend.arm else None
        if limits is not None:  # h = sign * [q, q'][source] + offset for every limit row
            n = limits.n_joints
            self._limit_source = limits.joint + np.repeat([0, n], 2 * n)
            top = limits.max_speed - limits.speed_margin
            self._limit_offset = np.concatenate([
                np.ravel(np.column_stack([-(limits.lower + limits.range_margin),
                                          limits.upper - limits.range_margin])),
                np.repeat(top, 2)])

    def _pair_table(self) -> tuple[np.ndarray, ...]:
        """The compiled pairs' ``(first, second, radius, fixed)``: each pair row's moving
        sphere, its other end (a sphere >= 0, obstacle ``o`` as ``-1 - o``, fixed sphere
        ``f`` as ``-1 - O - f``) and radius sum, and the fixed spheres' centres."""
        n_s, n_o = self.n_spheres, self.n_obstacles
        first = np.tile(np.arange(n_s), n_o)
        second = np.repeat(-1 - np.arange(n_o), n_s)
        radius, fixed = self._radius, np.zeros((0, 3))
        pairs = self.self_collision
        if pairs is not None:
            moving = pairs.second < n_s
            other = np.where(moving, pairs.second, -1 - n_o - (pairs.second - n_s))
            first = np.concatenate([first, pairs.first])
            second = np.concatenate([second, other])
            radius = np.concatenate([radius, pairs.radius])
            fixed = pairs.fixed
        return (np.ascontiguousarray(first, dtype=np.int64),
                np.ascontiguousarray(second, dtype=np.int64),
                np.ascontiguousarray(radius, dtype=np.float64),
                np.ascontiguousarray(fixed, dtype=np.float64))

    @property
    def layout(self) -> BarrierLayout:
        """The pairs of relative degree 2 with one learner each, then the joint-limit
        barriers sharing one learner per joint (``FrankaObstacleEnv.barrier_layout``)."""
        return arm_layout(self.n_pair_rows, self.limits)

    @property
    def shared_layout(self) -> BarrierLayout:
        """:attr:`layout` with every pair projected onto the seven joint learners
        (``learner="afvsgp-shared"``; ``FrankaObstacleEnv.shared_barrier_layout``): the terms
        carry ``projection`` (``n' J_s`` per pair; the robot's kinematics are known). Needs
        the joint limits."""
        return arm_layout(self.n_pair_rows, self.limits, projected=True)

    @property
    def filter_defaults(self) -> dict:
        """The :class:`~afvsgp_gym.cbf.FilterConfig` options the simulation suggests for the
        same barriers (``FrankaObstacleEnv.filter_defaults`` without the warm-up ones):
        activation distances, braking decelerations and first gains per barrier, and the
        joint-limit barriers' band correction."""
        k, lim = self.n_pair_rows, self.limits
        out = {"activation_distance": np.full(k, self.OBSTACLE_ACTIVATION),
               "braking_deceleration": np.full(k, self.OBSTACLE_DECELERATION),
               "first_gain": np.full(k, np.nan)}
        if lim is None:
            return out
        n = lim.n_joints
        out["activation_distance"] = np.concatenate([
            out["activation_distance"], np.full(2 * n, self.RANGE_ACTIVATION),
            np.full(2 * n, self.SPEED_ACTIVATION)])
        out["braking_deceleration"] = np.concatenate([
            out["braking_deceleration"], np.repeat(FRANKA_MAX_ACCELERATION, 2),
            np.full(2 * n, np.inf)])
        out["first_gain"] = np.concatenate([out["first_gain"], np.full(2 * n, np.nan),
                                            np.full(2 * n, self.SPEED_GAIN)])
        out.update(limit_calibration(k, n))  # the Franka envs' (one definition)
        return out

    def terms(self, q, qd, mass, coriolis, obstacles: ObstacleEstimate,
              spheres: tuple | None = None) -> BarrierSet:
        """The barriers' terms at joint angles ``q`` (7,) and velocities ``qd`` (7,), with the
        robot model's mass matrix ``mass`` (7, 7) and Coriolis vector ``coriolis`` (7,)
        (``C(q, q') q'``, Nm) and the obstacle estimate ``obstacles`` (O of them).
        ``spheres``: the spheres' ``kinematics(q, qd)`` when already computed."""
        q = _rows(q, (7,), "q")
        qd = _rows(qd, (7,), "qd")
        mass = _rows(mass, (7, 7), "mass")
        coriolis = _rows(coriolis, (7,), "coriolis")
        if not isinstance(obstacles, ObstacleEstimate) \
                or obstacles.position.shape[0] != self.n_obstacles:
            raise ValueError(f"obstacles must be an ObstacleEstimate of {self.n_obstacles} "
                             f"obstacles. Got: {obstacles!r}")
        p, v, jac, bias = self.kinematics(q, qd) if spheres is None else spheres
        # M^-1 itself: q''_0 = -M^-1 c and the gains J M^-1 (M symmetric)
        minv = np.linalg.inv(mass)
        qacc0 = -(minv @ coriolis)
        nb = self.n_barriers  # the pairs' rows, then the joint limits' (filled in place)
        lf = np.empty(nb)
        lg = np.empty((nb, 7))
        derivs = np.empty((nb, 2))
        xi = np.empty((nb, FEATURE_DIM))
        if self._pair_index is not None and self._shape_const is None \
                and obstacles.covariance is None:
            k, cov = self.n_pair_rows, None
            rows = self._compiled_pairs(q, qd, p, v, jac, bias, qacc0, minv, obstacles,
                                        derivs, lf, lg, xi)
            if self.limits is None:
                rows = None
        else:
            k, rows, cov = self._pair_terms(q, qd, p, v, jac, bias, qacc0, minv, obstacles,
                                            derivs, lf, lg, xi)
        lim, projection = self.limits, None
        if lim is not None:  # JointLimits.terms, .derivatives and .features, in place
            joint, sign = lim.joint, lim.sign
            lf[k:] = sign * qacc0[joint]
            lg[k:] = sign[:, None] * (minv * self.action_scale)[joint]
            derivs[k:, 0] = sign * np.concatenate((q, qd))[self._limit_source] + self._limit_offset
            r = k + 2 * lim.n_joints
            derivs[k:r, 1] = sign[: r - k] * qd[joint[: r - k]]
            derivs[r:, 1] = 0.0
            xi[k:, :7], xi[k:, 7:14] = q, qd
            xi[k:, 14:] = 0.0
            projection = joint_projection(rows, lim)
        if self._error_per_action.any():  # the worst residual torque within the bound
            lf -= np.abs(lg) @ self._error_per_action
        return BarrierSet(derivs, lf, lg, xi, cov, projection=projection)

    def _compiled_pairs(self, q, qd, p, v, jac, bias, qacc0, minv, obstacles, derivs, lf, lg,
                        xi) -> np.ndarray:
        """:meth:`_pair_terms` of a scene of spheres without a covariance in compiled code
        (``_arm.pair_terms``): fills the pair rows in place, returns their projection rows
        ``n'(J_a - J_b)``."""
        first, second, radius, fixed = self._pair_index
        n = self.n_pair_rows
        rows = np.empty((n, 7))
        c = np.ascontiguousarray
        _arm.pair_terms(self.n_spheres, n, self.n_obstacles, len(fixed), first, second, radius,
                        c(p, dtype=np.float64), c(v, dtype=np.float64),
                        c(jac, dtype=np.float64), c(bias, dtype=np.float64), qacc0,
                        c(obstacles.position), c(obstacles.velocity),
                        c(obstacles.acceleration), fixed, minv * self.action_scale, c(q),
                        c(qd), derivs[:n], lf[:n], lg[:n], xi[:n], rows)
        return rows

    def _pair_terms(self, q, qd, p, v, jac, bias, qacc0, minv, obstacles, derivs, lf, lg,
                    xi) -> tuple:
        """The pair rows (obstacle pairs, then self-collision pairs) of :meth:`terms` in
        numpy, in place; ``(first limit row, projection rows or None, covariance or
        None)``."""
        n_s, n_o, k = self.n_spheres, self.n_obstacles, self.n_pairs
        d = (p[None, :, :] - obstacles.position[:, None, :]).reshape(k, 3)
        vr = (v[None, :, :] - obstacles.velocity[:, None, :]).reshape(k, 3)
        h, hd, n, curv, offset, hess = self._pair_geometry(d, vr,
                                                          obstacles.covariance is not None)
        acc = jac @ qacc0 + bias  # (S, 3) sphere accelerations at zero action
        a_obs = np.repeat(obstacles.acceleration, n_s, axis=0)
        ns = n.reshape(n_o, n_s, 3)
        nb = self.n_barriers
        lf[:k] = np.einsum("osi,si->os", ns, acc).ravel()
        lf[:k] -= np.einsum("ki,ki->k", n, a_obs)
        lf[:k] += curv
        gain = np.matmul(jac, minv) * self.action_scale  # (S, 3, 7)
        lg[:k] = np.einsum("osi,sij->osj", ns, gain).reshape(k, 7)
        derivs[:k, 0], derivs[:k, 1] = h, hd
        xi[:k, :7], xi[:k, 7:14] = q, qd  # (the self rows' and limits' below)
        xi[:k, 14:17], xi[:k, 17:] = offset, vr
        cov = None
        if obstacles.covariance is not None:
            per_pair = np.repeat(obstacles.covariance, n_s, axis=0)
            w = np.tile(acc, (n_o, 1)) - a_obs
            cov = np.zeros((nb, 3, 3))
            cov[:k], bias = self._pair_covariance(d, n, vr, per_pair, w, hess)
            lf[:k] -= bias
        rows = (None if self.limits is None  # n' J_s per pair: the shared learner's
                else np.einsum("osi,sij->osj", ns, jac).reshape(k, 7))
        if self.self_collision is not None:
            k, rows = self._self_rows(k, q, qd, p, v, jac, acc, minv, lf, lg, derivs, xi,
                                      rows)
        return k, rows, cov

    def _self_rows(self, k, q, qd, p, v, jac, acc, minv, lf, lg, derivs, xi, rows):
        """Fill the self-collision rows after the ``k`` obstacle rows, in place; returns the
        first limit row and the pairs' projection rows ``n'(J_a - J_b)`` after ``rows`` (None
        without the limits: no projection). ``lg`` is those rows times ``M^-1
        diag(action_scale)`` (one product for the pairs, not one per sphere)."""
        pairs = self.self_collision
        end = k + len(pairs)
        geometry = pairs.geometry(p, v)
        pair_rows = pairs.rows(geometry, jac)
        lf[k:end] = pairs.lf(geometry, acc)
        lg[k:end] = pair_rows @ (minv * self.action_scale)
        derivs[k:end, 0], derivs[k:end, 1] = geometry.h, geometry.hd
        xi[k:end] = pairs.features(geometry, q, qd, FEATURE_DIM)
        return end, None if rows is None else np.concatenate([rows, pair_rows])

    def _pair_geometry(self, d: np.ndarray, vr: np.ndarray,
                       hessians: bool = False) -> tuple[np.ndarray | None, ...]:
        """``(h, h', n, curvature, offset, H)`` of the pairs at ``d = p_s - p_o`` and
        ``v_rel``: the sphere formulas for a scene of spheres, else ``pair_barriers`` (the
        simulation's ``FrankaObstacleEnv._pair_geometry``), with the signed distances'
        Hessians (K, 3, 3) when ``hessians`` (else None); ``offset`` the features' (``d`` for a
        sphere obstacle, else the sphere centre's offset from the closest surface point)."""
        if self._shape_const is None:
            h, hd, n, curv = sphere_barriers(d, vr, self._radius)
            return h, hd, n, curv, d, None
        stack, with_hessians, sphere_rad, sphere_rows = self._shape_const
        hess = None
        if hessians:  # one pass of the kernels for both
            h, hd, n, curv, hess = pair_barriers_and_hessians(with_hessians, d, vr, sphere_rad)
        else:
            h, hd, n, curv = pair_barriers(stack, d, vr, sphere_rad)
        offset = np.where(sphere_rows[:, None], d, n * (h + sphere_rad)[:, None])
        return h, hd, n, curv, offset, hess

    def _pair_covariance(self, d: np.ndarray, n: np.ndarray, vr: np.ndarray,
                         per_pair: np.ndarray, w: np.ndarray,
                         hess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The pairs' covariance of ``[h, h', lf]`` (K, 3, 3) and the mean of ``lf``'s error
        (K,) from the per-axis covariance ``per_pair`` of each pair's obstacle and, in a scene
        that is not spheres only, the signed distances' Hessians ``hess`` (module
        docstring)."""
        if hess is None:
            dist = np.linalg.norm(d, axis=1)
            return pair_covariance(n, dist, vr, per_pair, w), 2.0 * per_pair[:, 1, 1] / dist
        bias = per_pair[:, 1, 1] * np.einsum("kii->k", hess)
        return shape_pair_covariance(n, hess, vr, per_pair, w), bias

    def sphere_clearance(self, q, obstacle_positions) -> np.ndarray:
        """``h`` (O S,) of every pair at joint angles ``q`` and obstacle reference points
        (O, 3): the geometry alone (for checks of a true state)."""
        p = self.kinematics.positions(_rows(q, (7,), "q"))
        pos = _rows(obstacle_positions, (self.n_obstacles, 3), "obstacle_positions")
        d = (p[None, :, :] - pos[:, None, :]).reshape(-1, 3)
        if self._shape_const is None:
            return np.linalg.norm(d, axis=1) - self._radius
        return self._pair_geometry(d, np.zeros_like(d))[0]


def _check_shapes(shapes, obstacle_radii: np.ndarray) -> tuple:
    """``shapes`` as a tuple of O primitives or None (a ``Sphere`` becomes None); ValueError
    naming ``shapes[i]`` or ``obstacle_radii[i]`` unless each entry is None or a primitive
    whose bounding radius is that obstacle's radius."""
    o = len(obstacle_radii)
    if shapes is None:
        shapes = (None,) * o
    if isinstance(shapes, (str, bytes, Sphere, Box, Capsule, Plane)) or not hasattr(
            shapes, "__len__") or len(shapes) != o:
        raise ValueError(f"shapes must be None or a sequence of {o} entries (one per "
                         f"obstacle: a Box, Capsule, Plane, Sphere or None). Got: {shapes!r}")
    out = []
    for i, shape in enumerate(shapes):
        if shape is not None and not isinstance(shape, (Sphere, Box, Capsule, Plane)):
            raise ValueError(f"shapes[{i}] must be a Box, Capsule, Plane, Sphere "
                             f"(afvsgp_gym.envs.primitives) or None. Got: {shape!r}")
        if shape is not None and obstacle_radii[i] != bounding_radius(shape):
            raise ValueError(f"obstacle_radii[{i}] must be shapes[{i}]'s bounding radius "
                             f"{bounding_radius(shape)} (ObstacleSpec.radius). Got: "
                             f"{obstacle_radii[i]}")
        if shape is None and not np.isfinite(obstacle_radii[i]):
            raise ValueError(f"obstacle_radii[{i}] of a sphere must be finite. Got: "
                             f"{obstacle_radii[i]}")
        out.append(None if shape is None or isinstance(shape, Sphere) else shape)
    return tuple(out)


def panda_self_collision_pairs() -> SelfCollisionPairs:
    """The simulation's self-collision pairs of the Panda's 21 arm spheres and the base's two,
    the base's centres in the robot's base frame (link0's, where the base spheres are
    given)."""
    return SelfCollisionPairs.of(PANDA_SELF_COLLISION_SPHERES,
                                 fixed_centres=[s.offset for s in PANDA_BASE_SPHERES])
