"""PointMassObstacleEnv: barrier ground truth vs finite differences, API and scenarios."""

import copy
import math

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401  (registers the ids)
from afvsgp_gym.agents import NominalController
from afvsgp_gym.envs.point_mass import PointMassObstacleEnv
from afvsgp_gym.envs.scenario import CyclicReference, ObstacleSpec

ENV_ID = "afvsgp_gym/PointMassObstacle-v0"


def _near_state(env):
    """The point's position and velocity set by :func:`_env_near_moving_obstacle`."""
    po, _, _ = env.obstacles[0].state(env.time)
    return po + np.r_[0.2, -0.1, 0.05][: env.dim], np.random.default_rng(3).normal(size=env.dim)


def _env_near_moving_obstacle(dim=2, dt=1e-5, **kw):
    """An env mid-way through the dynamic obstacle's approach, close to the obstacle."""
    env = PointMassObstacleEnv("dynamic", dim=dim, dt=dt, warmup_steps=0, **kw)
    env.reset(seed=0)
    ob = env.obstacles[0]
    env.set_time_step(int(round(0.5 * ob.duration / dt)))  # peak speed, acceleration nearby
    env.set_state(*_near_state(env))
    return env


def _hd_after(env, u):
    e = copy.deepcopy(env)
    e.step(u)
    return e.barrier_terms("true")[0].derivatives


@pytest.mark.parametrize("dim", [2, 3])
def test_true_terms_match_finite_differences(dim):
    dt = 1e-5
    env = _env_near_moving_obstacle(dim=dim, dt=dt)
    t0 = env.barrier_terms("true")[0]
    zero = np.zeros(dim)
    d0 = _hd_after(env, zero)
    # h' from h, action-free part lf from h' with u = 0
    np.testing.assert_allclose((d0[0] - t0.derivatives[0]) / dt, t0.derivatives[1], rtol=1e-3)
    np.testing.assert_allclose((d0[1] - t0.derivatives[1]) / dt, t0.lf, rtol=1e-3, atol=1e-3)
    # action-dependent part lg from stepping with u = e_i at the same state
    for i in range(dim):
        di = _hd_after(env, np.eye(dim)[i])
        np.testing.assert_allclose((di[1] - d0[1]) / dt, t0.lg[i], rtol=1e-3, atol=1e-4)


def test_true_terms_independent_formula():
    env = _env_near_moving_obstacle(dim=3, dt=0.01)
    t = env.barrier_terms("true")[0]
    p, v = _near_state(env)
    po, vo, ao = env.obstacles[0].state(env.time)
    d, vr = p - po, v - vo
    dist = np.linalg.norm(d)
    h_fn = lambda p: np.linalg.norm(p - po) - env.obstacles[0].radius - env.agent_radius  # noqa: E731
    # Hessian of |d| by central differences gives the curvature term v' H v
    eps = 1e-5
    H = np.zeros((3, 3))
    for i in range(3):
        e = np.eye(3)[i] * eps
        g1 = np.array(
            [(h_fn(p + e + f) - h_fn(p + e - f)) / (2 * eps) for f in np.eye(3) * eps]
        )
        g0 = np.array(
            [(h_fn(p - e + f) - h_fn(p - e - f)) / (2 * eps) for f in np.eye(3) * eps]
        )
        H[i] = (g1 - g0) / (2 * eps)
    acc_free = -env.drag / env.mass * v
    lf_ref = d / dist @ (acc_free - ao) + vr @ H @ vr
    np.testing.assert_allclose(t.lf, lf_ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(t.lg, d / dist * env.max_force / env.mass, rtol=1e-12)
    np.testing.assert_allclose(t.xi, np.r_[p, v, d, vr])
    assert env.feature_dim == t.xi.shape[0] == 12


@pytest.mark.parametrize("nominal_model", ["zero", "kinematic", "perturbed", "exact"])
def test_delta_b_true_is_true_minus_nominal(nominal_model):
    env = _env_near_moving_obstacle(dim=2, dt=0.01, nominal_model=nominal_model)
    u = np.array([0.3, -0.7], dtype=np.float32)
    tt, tn = env.barrier_terms("true")[0], env.barrier_terms("nominal")[0]
    np.testing.assert_allclose(tn.derivatives, tt.derivatives)  # kinematics are known
    _, _, _, _, info = env.step(u)
    expected = (tt.lf + tt.lg @ u) - (tn.lf + tn.lg @ u)
    np.testing.assert_allclose(info["delta_b_true"], [expected], rtol=1e-12)
    if nominal_model == "exact":
        np.testing.assert_allclose(info["delta_b_true"], 0.0, atol=1e-12)
    if nominal_model == "zero":
        assert tn.lf == 0.0 and not np.any(tn.lg)
    if nominal_model == "kinematic":
        assert not np.any(tn.lg)


def test_obstacle_and_reference_derivatives():
    spec = ObstacleSpec(np.array([0.3, 0.04]), 0.1, np.array([0.3, 0.8]), 3.0, 0.3)
    ts = np.linspace(2.0, 3.0 + spec.duration + 1.0, 2001)
    pos = np.array([spec.state(t)[0] for t in ts])
    vel = np.array([spec.state(t)[1] for t in ts])
    acc = np.array([spec.state(t)[2] for t in ts])
    np.testing.assert_allclose(pos[0], spec.start)
    np.testing.assert_allclose(pos[-1], spec.position)
    np.testing.assert_allclose(np.max(np.linalg.norm(vel, axis=1)), 0.3, rtol=1e-3)
    step = ts[1] - ts[0]
    np.testing.assert_allclose(np.gradient(pos, step, axis=0)[1:-1], vel[1:-1], atol=2e-4)
    np.testing.assert_allclose(np.gradient(vel, step, axis=0)[1:-1], acc[1:-1], atol=2e-3)
    ref = CyclicReference(
        np.zeros(3), np.eye(3)[1], np.eye(3)[2], 0.2, 0.05, 2.0, 1.0, 1.0, 3.0, 0.5
    )
    ts = np.linspace(0.0, 5.0, 5001)
    st = [ref.state(t) for t in ts]
    pos, vel, acc = (np.array([s[k] for s in st]) for k in range(3))
    step = ts[1] - ts[0]
    np.testing.assert_allclose(np.gradient(pos, step, axis=0)[1:-1], vel[1:-1], atol=1e-4)
    # the blends' jerk jumps at their ends (O(step * jerk) difference error there)
    np.testing.assert_allclose(np.gradient(vel, step, axis=0)[1:-1], acc[1:-1], atol=5e-2)
    assert np.abs(acc).max() > 1.0
    assert np.allclose(pos[:1000, 2], 0.0) and np.allclose(pos[-1000:, 1], 0.0)  # y, then z


def _rollout(env, seed, steps, policy=None):
    obs, _ = env.reset(seed=seed)
    policy = policy or NominalController(env)
    out, hs = [obs], []
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(policy(obs))
        out.append(obs)
        hs.append(info["h"])
        if term or trunc:
            break
    return np.array(out), np.array(hs)


def test_determinism_under_seed():
    a, _ = _rollout(gym.make(ENV_ID, scenario="random"), 7, 400)
    b, _ = _rollout(gym.make(ENV_ID, scenario="random"), 7, 400)
    c, _ = _rollout(gym.make(ENV_ID, scenario="random"), 8, 400)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("scenario", ["static", "dynamic", "random"])
def test_warmup_keeps_obstacles_far_and_reference_hits_them(scenario):
    for seed in range(4 if scenario == "random" else 1):
        env = gym.make(ENV_ID, scenario=scenario)
        _, hs = _rollout(env, seed, 1500)
        warm = env.unwrapped.warmup_steps
        assert warm >= 250
        assert hs[:warm].min() > 0.05
        assert hs.min() < 0.0  # the unfiltered tracker collides: the filter has work to do


def test_reward_is_sum_of_terms_and_info_keys():
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    _, r, _, _, info = env.step(env.action_space.sample())
    assert r == info["reward_tracking"] + info["reward_ctrl"]
    keys = ("cost", "h", "h_per_barrier", "collision", "tracking_error", "reference_h",
            "delta_b_true", "unstable")
    for key in keys:
        assert key in info
    assert info["delta_b_true"].shape == (1,) and isinstance(info["h"], float)
    base = env.unwrapped
    assert base.relative_degree == 2 and base.n_obstacles == base.n_barriers == 1
    assert base.dt == 0.01
    assert base.metadata["render_fps"] == 100


def test_bad_input():
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    base = env.unwrapped
    p, v, k = base._p.copy(), base._v.copy(), base._steps
    for bad in ([np.nan, 0.0], [np.inf, 0.0], [0.0, 0.0, 0.0], "ab"):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    np.testing.assert_array_equal(base._p, p)
    np.testing.assert_array_equal(base._v, v)
    assert base._steps == k
    with pytest.raises(ValueError, match="static"):
        gym.make(ENV_ID, scenario="nope")
    with pytest.raises(ValueError, match="nominal_model"):
        gym.make(ENV_ID, nominal_model="nope")
    with pytest.raises(TypeError, match="valid"):
        gym.make(ENV_ID, bogus=1)
    with pytest.raises(ValueError, match="model"):
        base.barrier_terms("nope")


def test_out_of_range_actions_are_clipped():
    e1, e2 = (gym.make(ENV_ID) for _ in range(2))
    e1.reset(seed=0)
    e2.reset(seed=0)
    o1 = e1.step(np.array([5.0, -3.0]))[0]
    o2 = e2.step(np.array([1.0, -1.0]))[0]
    np.testing.assert_array_equal(o1, o2)


def test_multiple_obstacles_and_render():
    obstacles = [
        {"position": [0.35, 0.0], "radius": 0.05},
        {"position": [-0.3, 0.0], "radius": 0.08, "start": [-0.3, 0.9], "speed": 0.2},
    ]
    env = gym.make(ENV_ID, obstacles=obstacles, render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    assert env.unwrapped.n_barriers == 2 and obs.shape == env.observation_space.shape
    _, _, _, _, info = env.step(np.zeros(2))
    assert info["h_per_barrier"].shape == (2,) and info["delta_b_true"].shape == (2,)
    assert len(env.unwrapped.barrier_terms()) == 2
    img = env.render()
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    with pytest.raises(ValueError, match="radius"):
        gym.make(ENV_ID, obstacles=[{"position": [0.0, 0.0]}])


# the terms at the poked state are inf - inf = NaN (the step flags them), and numpy says so
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_unstable_state_ends_episode():
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    env.unwrapped._v[:] = np.inf
    _, _, term, _, info = env.step(np.zeros(2))
    assert term and info["unstable"]


def test_perturbed_model_with_true_parameters_is_exact():
    env = _env_near_moving_obstacle(
        dt=0.01, nominal_model="perturbed", nominal_mass=1.5, nominal_drag=0.8
    )
    _, _, _, _, info = env.step(np.array([0.2, -0.4]))
    np.testing.assert_allclose(info["delta_b_true"], 0.0, atol=1e-12)


def test_backup_action_brakes_the_point():
    env = gym.make("afvsgp_gym/PointMassObstacle-v0", nominal_model="zero").unwrapped
    env.reset(seed=0)
    env.set_state(env._p, [0.4, -0.3])
    u = env.backup_action()
    np.testing.assert_allclose(u, [-0.8, 0.6])
    speeds = []
    for _ in range(60):
        env.step(env.backup_action().astype(np.float32))
        speeds.append(np.linalg.norm(env._v))
    assert speeds[-1] < 0.05 * 0.5 and np.all(np.diff(speeds) <= 1e-12)


@pytest.mark.parametrize("env_id", ["afvsgp_gym/PointMassObstacle-v0",
                                    "afvsgp_gym/FrankaObstacleStatic-v0"])
@pytest.mark.parametrize("gain", [-1.0, float("nan"), "fast"])
def test_bad_brake_gain_names_the_argument(env_id, gain):
    with pytest.raises(ValueError, match="brake_gain"):
        gym.make(env_id, brake_gain=gain)


def test_a_stopped_obstacle_comes_to_rest_smoothly_along_its_path():
    """ObstacleSpec.stopped_at: the same motion up to the stop, then the speed blended to
    zero over STOP_DURATION (half the speed times it travelled): position, velocity and
    acceleration continuous, velocity and acceleration the derivatives of position and
    velocity (central differences), and at rest on the original path afterwards."""
    from afvsgp_gym.envs.scenario import STOP_DURATION

    ob = ObstacleSpec(np.array([0.5, 0.0, 0.4]), 0.05, np.array([1.0, 0.0, 0.4]), 1.0, 0.2,
                      yield_distance=0.05)
    ts = ob.start_time + 0.4 * ob.duration
    assert ob.yields_at(ts) and not ob.yields_at(0.5) and not ob.yields_at(99.0)
    st = ob.stopped_at(ts)
    assert not st.yields_at(ts + 0.1)
    with pytest.raises(ValueError, match="t"):
        ob.stopped_at(math.nan)
    for t in (0.5, ts - 0.1, ts):
        for a, b in zip(st.state(t), ob.state(t), strict=True):
            np.testing.assert_array_equal(a, b)
    eps = 1e-7  # both sides of the stop and inside the blend: derivatives continuous
    for a, b in zip(st.state(ts + eps), st.state(ts), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-5)
    h = 1e-5
    for t in (ts + 0.3 * STOP_DURATION, ts + 0.7 * STOP_DURATION):
        p0, v0, a0 = st.state(t)
        (pm, vm, _), (pp, vp, _) = st.state(t - h), st.state(t + h)
        np.testing.assert_allclose((pp - pm) / (2 * h), v0, atol=1e-8)
        np.testing.assert_allclose((vp - vm) / (2 * h), a0, atol=1e-6)
    p_end, v_end, a_end = st.state(ts + STOP_DURATION + 1.0)
    assert np.all(v_end == 0.0) and np.all(a_end == 0.0)
    travelled = np.linalg.norm(p_end - ob.state(ts)[0])
    speed = np.linalg.norm(ob.state(ts)[1])
    assert speed * STOP_DURATION / 2 * 0.9 < travelled < speed * STOP_DURATION / 2 * 1.1
    on_path = ob.state(ts + STOP_DURATION / 2)[0]  # sigma = ts + T/2 at rest
    np.testing.assert_allclose(p_end, on_path, atol=1e-12)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="yield_distance"):
            ObstacleSpec(np.zeros(3), 0.1, np.ones(3), yield_distance=bad)
