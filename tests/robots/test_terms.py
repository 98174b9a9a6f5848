"""The barrier terms from a model equal the simulation's own at the same state (exact model)."""

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, sphere_arrays
from afvsgp_gym.robots.kinematics import GYMNASIUM_PANDA, SphereKinematics
from afvsgp_gym.robots.run import make_controller
from afvsgp_gym.robots.terms import BarrierModel, ObstacleEstimate, panda_self_collision_pairs


@pytest.fixture(scope="module", params=[True, False], ids=["self-collision", "obstacles"])
def env(request):
    # the exact model of a plant whose gravity the robot compensates fully: no payload,
    # catalogue masses, no damping or friction (the rotor armature stays in M); with the
    # self-collision barriers (the default) and without
    e = FrankaObstacleEnv("dynamic", nominal_model="exact", payload_mass=0.0, mass_scale=1.0,
                          damping=0.0, friction=0.0, normalize_action=False,
                          self_collision=request.param)
    e.reset(seed=0)
    yield e
    e.close()


def _bridge_model(env):
    lim = env.joint_limits
    kin = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES)
    radii = sphere_arrays(PANDA_ARM_SPHERES)[2]
    pairs = panda_self_collision_pairs() if env.self_collision else None
    return BarrierModel(kin, radii, [ob.radius for ob in env.obstacles], lim,
                        env.action_scale, self_collision=pairs)


def _model_of(env):
    """``M`` and ``c = C q'`` of the plant at its state (gravity cancelled by gravcomp)."""
    m, d = env.model, env.data
    full = np.empty((m.nv, m.nv))
    for i, e in enumerate(np.eye(m.nv)):  # M e_i, column by column (any MuJoCo version)
        mujoco.mj_mulM(m, d, full[i], e)
    return full, d.qfrc_bias - d.qfrc_passive


def _states(env, n, seed):
    rng = np.random.default_rng(seed)
    lim = env.joint_limits
    for i in range(n):
        q = rng.uniform(lim.lower + 0.05, lim.upper - 0.05)
        if i % 2:  # near the ready pose: the spheres close to the obstacle's path
            q = env.q_home + rng.uniform(-0.3, 0.3, 7)
        yield q, rng.uniform(-1.5, 1.5, 7), int(rng.integers(0, 1500))


@pytest.mark.parametrize("with_covariance", [False, True])
def test_terms_equal_the_simulations(env, with_covariance):
    base = env.unwrapped
    model = _bridge_model(base)
    rng = np.random.default_rng(5)
    for q, qd, step in _states(base, 40, 4 + with_covariance):
        base.set_time_step(step)  # the moving obstacle somewhere on its path
        base.set_state(q, qd)
        states = base._obstacle_states
        pos = np.array([s[0] for s in states])
        vel = np.array([s[1] for s in states])
        acc = np.array([s[2] for s in states])
        cov = None
        if with_covariance:
            a = rng.normal(size=(len(states), 3, 3)) * 0.05
            cov = a @ a.transpose(0, 2, 1)
            base.set_obstacle_estimate(pos, vel, acc, cov)
        want = base.barrier_terms("nominal")
        mass, coriolis = _model_of(base)
        got = model.terms(q, qd, mass, coriolis, ObstacleEstimate(pos, vel, acc, cov))
        np.testing.assert_allclose(got.derivatives, want.derivatives, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.xi, want.xi, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.lg, want.lg, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got.lf, want.lf, rtol=1e-9, atol=1e-9)
        # the shared learner's projection: n' J_s (m/rad, |.| <= ~1) and the limits' signs
        np.testing.assert_allclose(got.projection, want.projection, rtol=0, atol=1e-12)
        if with_covariance:
            np.testing.assert_allclose(got.covariance, want.covariance, rtol=1e-9, atol=1e-14)
        else:
            assert got.covariance is None and want.covariance is None


def test_layout_names_and_filter_defaults_are_the_simulations(env):
    base = env.unwrapped
    model = _bridge_model(base)
    n_self = 93 if base.self_collision else 0
    assert model.n_barriers == base.n_barriers == 21 + n_self + 28
    for got, want in ((model.layout, base.barrier_layout),
                      (model.shared_layout, base.shared_barrier_layout)):
        for key in ("relative_degree", "learner", "sign", "group"):
            np.testing.assert_array_equal(getattr(got, key), getattr(want, key))
    shared = make_controller(model, "afvsgp-shared")  # the robot runs the shared learner too
    assert shared.layout.projected.sum() == 21 + n_self and shared.layout.n_learners == 7
    sim = base.filter_defaults
    for key, value in model.filter_defaults.items():
        if isinstance(value, tuple):
            assert value == sim[key]
        else:
            np.testing.assert_array_equal(value, sim[key])


def test_clearance_is_the_terms_h(env):
    base = env.unwrapped
    model = _bridge_model(base)
    q, qd = base.q_home, np.zeros(7)
    pos = np.array([[0.4, 0.1, 0.4]])
    terms = model.terms(q, qd, np.eye(7), np.zeros(7), ObstacleEstimate(pos, np.zeros((1, 3)),
                                                                        np.zeros((1, 3))))
    np.testing.assert_allclose(model.sphere_clearance(q, pos), terms.h[:21], atol=1e-15)


def test_bad_input_names_the_argument(env):
    model = _bridge_model(env.unwrapped)
    est = ObstacleEstimate(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="mass"):
        model.terms(np.zeros(7), np.zeros(7), np.eye(6), np.zeros(7), est)
    with pytest.raises(ValueError, match="velocity"):
        ObstacleEstimate(np.zeros((2, 3)), np.zeros((1, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="obstacles"):
        model.terms(np.zeros(7), np.zeros(7), np.eye(7), np.zeros(7),
                    ObstacleEstimate(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3))))
    hand = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES[14:])
    for pairs, kin in ((True, model.kinematics), (panda_self_collision_pairs(), hand)):
        with pytest.raises(ValueError, match="self_collision must be the SelfCollisionPairs"):
            BarrierModel(kin, np.full(len(kin.links), 0.05), [0.05], None,
                         self_collision=pairs)


def test_torque_error_lowers_lf_by_the_worst_residual(env):
    base = env.unwrapped
    exact = _bridge_model(base)
    bound = np.array([3.0, 3.0, 3.0, 3.0, 1.0, 1.0, 1.0])
    robust = BarrierModel(exact.kinematics, exact.sphere_radii, exact.obstacle_radii,
                          exact.limits, torque_error=bound,
                          self_collision=exact.self_collision)
    rng = np.random.default_rng(9)
    q, qd = base.q_home + rng.uniform(-0.2, 0.2, 7), rng.uniform(-1, 1, 7)
    mass = np.diag(rng.uniform(0.5, 2.0, 7))
    est = ObstacleEstimate([[0.4, 0.1, 0.4]], np.zeros((1, 3)), np.zeros((1, 3)))
    a = exact.terms(q, qd, mass, np.ones(7), est)
    b = robust.terms(q, qd, mass, np.ones(7), est)
    np.testing.assert_allclose(b.lf, a.lf - np.abs(a.lg) @ bound, rtol=1e-12, atol=1e-12)
    # the worst residual within the bound, per barrier: tau_res = -bound sign(lg_k)
    for k in range(len(a.lf)):
        residual = -bound * np.sign(a.lg[k])
        assert a.lf[k] + a.lg[k] @ residual == pytest.approx(b.lf[k], abs=1e-12)
    np.testing.assert_array_equal(b.lg, a.lg)
    with pytest.raises(ValueError, match="torque_error"):
        BarrierModel(exact.kinematics, exact.sphere_radii, exact.obstacle_radii, exact.limits,
                     torque_error=-1.0)
