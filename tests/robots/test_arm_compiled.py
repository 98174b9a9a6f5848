"""The bridge's compiled geometry (afvsgp_gym.robots._arm) against its numpy reference: the
sphere kinematics and the sphere pairs' terms at random and ill-conditioned states, the
backend switch, and what stays on the numpy path."""

import numpy as np
import pytest

from afvsgp_gym import _compiled
from afvsgp_gym.envs.joint_limits import JointLimits
from afvsgp_gym.envs.primitives import Box
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, sphere_arrays
from afvsgp_gym.envs.scenario import bounding_radius
from afvsgp_gym.robots import kinematics, terms
from afvsgp_gym.robots.kinematics import (
    END_EFFECTOR_OFFSET,
    FRANKA_PANDA,
    GYMNASIUM_PANDA,
    SphereKinematics,
)
from afvsgp_gym.robots.terms import BarrierModel, ObstacleEstimate, panda_self_collision_pairs

BUILT = _compiled.extension("arm") is not None
needs_arm = pytest.mark.skipif(not BUILT, reason="afvsgp_gym.robots._arm not built")
EPS = np.finfo(np.float64).eps
RADII = sphere_arrays(PANDA_ARM_SPHERES)[2]
LIMITS = JointLimits(lower=[-2.9, -1.76, -2.9, -3.07, -2.9, -0.02, -2.9],
                     upper=[2.9, 1.76, 2.9, -0.07, 2.9, 3.75, 2.9],
                     max_speed=[2.175] * 4 + [2.61] * 3)


def _kinematics(chain, backend):
    """The bridge's points: the 21 spheres and the end-effector point."""
    links = [*SphereKinematics.from_spheres(chain, PANDA_ARM_SPHERES).links, 7]
    offsets = np.vstack([[s.offset for s in PANDA_ARM_SPHERES], END_EFFECTOR_OFFSET])
    return SphereKinematics(chain, links, offsets, backend=backend)


def _close(compiled, reference, bound, name):
    """|compiled - reference| within ``bound`` (elementwise or scalar)."""
    err = np.abs(compiled - reference)
    assert np.all(err <= bound), f"{name}: {err.max():.3g} above its bound"


@needs_arm
@pytest.mark.parametrize("chain", [GYMNASIUM_PANDA, FRANKA_PANDA], ids=lambda c: c.name)
def test_kinematics_equals_the_numpy_path(chain):
    """Positions, velocities, Jacobians and J' q' at 300 random states, up to the joint speed
    limits and beyond: the two paths sum the same products over the chain in other orders, so
    they agree to a few hundred roundings of each output's scale (|p| ~ 1 m, |J| ~ 1 m,
    |v| ~ |J| |q'|, |J' q'| ~ |J| |q'|^2)."""
    kn, kc = _kinematics(chain, "numpy"), _kinematics(chain, "compiled")
    assert kc.backend.arm and not kn.backend.arm
    rng = np.random.default_rng(0)
    for _ in range(300):
        q = rng.uniform(-3.2, 3.2, 7)
        qd = rng.uniform(-5.0, 5.0, 7)
        speed = np.abs(qd).sum()
        for name, a, b, scale in zip(("p", "v", "jac", "acc"), kn(q, qd), kc(q, qd),
                                     (1.0, speed, 1.0, speed * speed), strict=True):
            assert b.shape == a.shape and b.dtype == np.float64
            _close(b, a, 256 * EPS * scale, name)


@needs_arm
def test_kinematics_at_rest_and_at_the_zero_pose():
    """q' = 0 gives v = J' q' = 0 exactly; at q = 0 the points sit where the numpy path puts
    them."""
    kc, kn = _kinematics(GYMNASIUM_PANDA, "compiled"), _kinematics(GYMNASIUM_PANDA, "numpy")
    p, v, jac, acc = kc(np.zeros(7), np.zeros(7))
    assert not v.any() and not acc.any()
    _close(p, kn(np.zeros(7), np.zeros(7))[0], 8 * EPS, "p")
    # a point on link 1 moves with joint 1 alone
    assert not jac[0][:, 1:].any()


def _models(backend, *, self_collision=False, torque_error=0.0, limits=LIMITS, scale=1.0):
    kin = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES, backend=backend)
    return BarrierModel(kin, RADII, [0.05, 0.08, 0.12], limits, scale, torque_error,
                        self_collision=panda_self_collision_pairs() if self_collision else None,
                        backend=backend)


def _state(rng, cond=1e2):
    """A random state and a mass matrix of condition number ``cond``."""
    q = rng.uniform(LIMITS.lower, LIMITS.upper)
    qd = rng.uniform(-2.0, 2.0, 7)
    basis, _ = np.linalg.qr(rng.normal(size=(7, 7)))
    mass = (basis * np.geomspace(1.0, 1.0 / cond, 7)) @ basis.T
    est = ObstacleEstimate(rng.uniform(-0.6, 0.8, (3, 3)), rng.normal(size=(3, 3)),
                           rng.normal(size=(3, 3)))
    return q, qd, 0.5 * (mass + mass.T), rng.normal(size=7), est


def _bounds(model, q, qd, mass, coriolis, est):
    """Forward-error bounds of the outputs the two paths sum in other orders: ``lg`` is
    ``n'(J M^-1 diag(s))`` in numpy and ``(n'J)(M^-1 diag(s))`` compiled, so they differ by
    up to a few roundings of ``|n|'|J||M^-1| diag(s)`` (large where M is ill-conditioned),
    and ``lf`` by those of its terms plus the torque bound's ``|lg| tau_bar``."""
    p, v, jac, acc = model.kinematics(q, qd)
    minv = np.linalg.inv(mass)
    n_s = len(p)
    absj = np.abs(jac)  # |n_i| <= 1
    gain = np.einsum("sij,jk->sik", absj, np.abs(minv) * model.action_scale).sum(axis=1)
    lg_pairs = np.tile(gain, (model.n_obstacles, 1))
    if model.self_collision is not None:
        pr = model.self_collision
        other = np.where(pr.second[:, None] < n_s, gain[np.minimum(pr.second, n_s - 1)], 0.0)
        lg_pairs = np.vstack([lg_pairs, gain[pr.first] + other])
    lg = np.vstack([lg_pairs, np.abs(minv * model.action_scale)[model.limits.joint]])
    lg_bound = 64 * EPS * lg
    scale = 1.0 + np.abs(acc).max() + np.abs(v).max() ** 2 + np.abs(est.acceleration).max() \
        + np.abs(jac).max() * np.abs(minv).max() * np.abs(est.velocity).max()
    lf_bound = 64 * EPS * (scale + np.abs(jac).max() * (np.abs(minv) @ np.abs(coriolis)).max())
    lf_bound = lf_bound + lg_bound @ model._error_per_action * 2
    return lg_bound, lf_bound


@needs_arm
@pytest.mark.parametrize("self_collision", [False, True], ids=["obstacles", "self-collision"])
@pytest.mark.parametrize("torque_error", [0.0, 3.0], ids=["exact", "torque-bound"])
@pytest.mark.parametrize("cond", [1e2, 1e9], ids=["cond-1e2", "cond-1e9"])
def test_pair_terms_equal_the_numpy_path(self_collision, torque_error, cond):
    """Every row of ``BarrierModel.terms`` (obstacle pairs, self-collision pairs, joint
    limits) compiled and in numpy at 60 random states, with a well- and an ill-conditioned
    mass matrix, within the forward-error bounds of the two orders of summation (each
    path computes its own kinematics)."""
    rng = np.random.default_rng(int(cond) % 97 + 3 * self_collision)
    mn = _models("numpy", self_collision=self_collision, torque_error=torque_error,
                 scale=np.array([87.0] * 4 + [12.0] * 3))
    mc = _models("compiled", self_collision=self_collision, torque_error=torque_error,
                 scale=np.array([87.0] * 4 + [12.0] * 3))
    for _ in range(60):
        q, qd, mass, coriolis, est = _state(rng, cond)
        a, b = mn.terms(q, qd, mass, coriolis, est), mc.terms(q, qd, mass, coriolis, est)
        lg_bound, lf_bound = _bounds(mn, q, qd, mass, coriolis, est)
        # positions and velocities carry the kinematics' rounding (the paths' own)
        state_bound = 256 * EPS * (1.0 + np.abs(qd).sum())
        _close(b.derivatives, a.derivatives, state_bound, "h, h'")
        _close(b.xi, a.xi, state_bound, "xi")
        _close(b.lg, a.lg, lg_bound, "lg")
        _close(b.lf, a.lf, lf_bound, "lf")
        _close(b.projection, a.projection, 64 * EPS * (1 + np.abs(a.projection)),
               "projection")
        assert b.covariance is None and a.covariance is None


@needs_arm
def test_pair_terms_where_a_sphere_touches_an_obstacle_centre():
    """|d| -> 0: the normal is d / max(|d|, 1e-9) on both paths (the same clamp), so a sphere
    centre 1e-7 m and exactly 0 m from an obstacle's centre gives the same rows."""
    mn, mc = _models("numpy"), _models("compiled")
    q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
    qd = np.full(7, 0.2)
    p = mn.kinematics(q, qd)[0]
    for gap in (1e-7, 0.0):
        pos = np.vstack([p[5] + gap, [0.5, 0.5, 0.5], [0.0, 0.0, 2.0]])
        est = ObstacleEstimate(pos, np.zeros((3, 3)), np.zeros((3, 3)))
        a = mn.terms(q, qd, np.eye(7), np.zeros(7), est)
        b = mc.terms(q, qd, np.eye(7), np.zeros(7), est)
        assert np.isfinite(b.lf).all() and np.isfinite(b.derivatives).all()
        big = 1.0 + np.abs(a.lf)
        _close(b.lf, a.lf, 1e3 * EPS * big, "lf")
        _close(b.derivatives, a.derivatives, 64 * EPS * (1 + np.abs(a.derivatives)), "h")


class _Refuse:
    """An extension module whose every function refuses to be called."""

    def __init__(self, calls):
        self.calls = calls

    def __getattr__(self, attr):
        self.calls.append(attr)
        raise AssertionError(f"the numpy path called _arm.{attr}")


def test_backend_numpy_and_the_cases_compiled_code_does_not_cover_run_numpy(monkeypatch):
    """``backend="numpy"`` never calls the extension; with ``"auto"``, an obstacle covariance
    or a non-sphere obstacle takes the numpy path (the compiled pairs cover spheres
    without a covariance)."""
    calls = []
    monkeypatch.setattr(kinematics, "_arm", _Refuse(calls))
    monkeypatch.setattr(terms, "_arm", _Refuse(calls))
    rng = np.random.default_rng(5)
    q, qd, mass, coriolis, est = _state(rng)
    out = _models("numpy", self_collision=True).terms(q, qd, mass, coriolis, est)
    assert out.lf.shape == (3 * 21 + 93 + 28,)
    cov = ObstacleEstimate(est.position, est.velocity, est.acceleration,
                           np.tile(1e-4 * np.eye(3), (3, 1, 1)))
    kin = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES, backend="numpy")
    box = Box(np.zeros(3), np.eye(3), np.array([0.05, 0.05, 0.05]))
    if BUILT:  # the terms' own switch on, the kinematics' off
        for model in (BarrierModel(kin, RADII, [0.05, 0.08, 0.12], LIMITS, backend="auto"),
                      BarrierModel(kin, RADII, [0.05, bounding_radius(box), 0.12], LIMITS,
                                   shapes=[None, box, None], backend="auto")):
            assert model.backend.arm
            model.terms(q, qd, mass, coriolis, cov if model.shapes[1] is None else est)
    assert not calls


def test_backend_compiled_without_the_extension_is_an_import_error(without_extensions):
    without_extensions("arm")
    with pytest.raises(ImportError, match=r"afvsgp_gym\.robots\._arm, which was not built"):
        SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES, backend="compiled")
    with pytest.raises(ValueError, match="backend must be one of"):
        _models("fast")
    assert not _models("auto").backend.arm


@needs_arm
def test_the_extension_refuses_arrays_of_the_wrong_size_naming_them():
    arm = _compiled.extension("arm")
    k = _kinematics(GYMNASIUM_PANDA, "compiled")
    n = len(k.links)
    out = [np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 7)), np.empty((n, 3))]
    with pytest.raises(ValueError, match="offsets must hold"):
        arm.kinematics(n, np.zeros(7), np.zeros(7), *k._chain_c, k._frame,
                       np.zeros((n - 1, 3)), *out)
    with pytest.raises(ValueError, match="frame must be of dtype int64"):
        arm.kinematics(n, np.zeros(7), np.zeros(7), *k._chain_c, k._frame.astype(float),
                       k.offsets, *out)
    bad = k._frame.copy()
    bad[0] = 7
    with pytest.raises(ValueError, match="frame must hold link indices 0-6"):
        arm.kinematics(n, np.zeros(7), np.zeros(7), *k._chain_c, bad, k.offsets, *out)
