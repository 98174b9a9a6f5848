"""Sensing and pushes on the Franka envs: the observation and the filter's terms carry the
configured noise, rate and delay (measured error statistics), the safety figures in ``info``
stay the true ones, pushes act, the sensing covariance is the first-order propagation of the
estimate's, and bad options are refused by name."""

import gymnasium as gym
import numpy as np
import pytest
from scipy import stats

import afvsgp_gym  # noqa: F401
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.perception import Perception, pair_covariance
from afvsgp_gym.envs.scenario import sphere_barriers

STATIC = "afvsgp_gym/FrankaObstacleStatic-v0"
DYNAMIC = "afvsgp_gym/FrankaObstacleDynamic-v0"


def _chi2_band(n: int, p: float = 1e-4) -> tuple[float, float]:
    """Where ``sum of n squared standard normals / n`` lies with probability ``1 - p``."""
    return stats.chi2.ppf(p / 2, n) / n, stats.chi2.ppf(1 - p / 2, n) / n


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"obstacle_noise": -0.01}, "obstacle_noise"),
    ({"obstacle_noise": float("nan")}, "obstacle_noise"),
    ({"obstacle_rate": 0.0}, "obstacle_rate"),
    ({"obstacle_rate": -30.0}, "obstacle_rate"),
    ({"obstacle_delay": -0.03}, "obstacle_delay"),
    ({"velocity_noise": -1.0}, "velocity_noise"),
    ({"position_noise": "a"}, "position_noise"),
    ({"push": {"force": 10.0, "duration": 0.1, "rate": 0.5, "torque": 1.0}}, "torque"),
    ({"push": {"force": 10.0, "rate": 0.5}}, "duration"),
    ({"push": {"force": 10.0, "duration": 0.0, "rate": 0.5}}, "duration"),
    ({"push": 10.0}, "push"),
])
def test_bad_sensing_options_are_refused_by_name(kwargs, name):
    with pytest.raises(ValueError, match=name):
        gym.make(STATIC, **kwargs)


def test_defaults_sense_exactly():
    """The defaults (0 or None) are today's env: one view of the state, no covariance."""
    env = FrankaObstacleEnv("dynamic")
    env.reset(seed=0)
    assert env.perception.exact and env._sensed_view is env._true_view
    assert env.barrier_terms("nominal").covariance is None
    assert not Perception(push={"force": 0.0, "duration": 0.1, "rate": 1.0}).pushes


def test_camera_noise_rate_and_delay_are_what_was_asked():
    """Dynamic obstacle, 1 cm noise, 30 Hz, 60 ms: the observed centre is the true centre at
    the newest sample's time (held between samples) plus noise whose per-axis variance is 1 cm^2
    within a chi-square band, and the filter's terms see the same reading."""
    noise, rate, delay = 0.01, 30.0, 0.06
    env = gym.make(DYNAMIC, obstacle_noise=noise, obstacle_rate=rate, obstacle_delay=delay)
    base = env.unwrapped
    obs, _ = env.reset(seed=1)
    errors, changes, prev = [], 0, None
    zero = np.zeros(7, dtype=np.float32)
    for _ in range(1500):
        obs, *_ = env.step(zero)
        seen = obs[20:23].astype(np.float64)
        k = np.floor((base.time - delay) * rate + 1e-9)
        truth = base.obstacles[0].state(k / rate)[0]
        errors.append(seen - truth)
        changes += prev is not None and not np.array_equal(seen, prev)
        prev = seen
        nominal = base.barrier_terms("nominal")
        h_pair = nominal.h[0]  # the first sphere against the obstacle as read
        p_s = base._sensed_view.spheres[0][0]
        expected = np.linalg.norm(p_s - base._sensed_view.obstacle_states[0][0])
        assert h_pair == pytest.approx(expected - base._obstacle_radii[0]
                                       - base._sphere_radii[0], abs=1e-12)
    err = np.array(errors)
    assert np.abs(err).max() < 6 * noise + 1e-3  # float32 observation
    lo, hi = _chi2_band(err.size // 8)  # samples repeat ~8 steps: the independent ones
    assert lo < (err ** 2).mean() / noise ** 2 < hi
    assert changes == pytest.approx(1500 * 0.004 * rate, abs=2)
    info_h = env.step(zero)[4]["h"]
    assert info_h == pytest.approx(base.true_state_terms("true").h[:base.n_obstacle_barriers]
                                   .min(), abs=0)


def test_encoders_noise_reaches_the_observation_and_the_terms_not_info():
    """0.02 rad/s and 1 mrad: the observed q and q' differ from the true ones by that much
    (chi-square band), the speed barriers' h are those of the measured q', and ``info``'s h,
    cost and limit check are computed from the true state."""
    sv, sq = 0.02, 0.001
    env = gym.make(STATIC, velocity_noise=sv, position_noise=sq)
    base = env.unwrapped
    env.reset(seed=2)
    dq, dqd = [], []
    zero = np.zeros(7, dtype=np.float32)
    for _ in range(200):
        obs, _, _, _, info = env.step(zero)
        dq.append(obs[:7] - base.data.qpos[:7])
        dqd.append(obs[7:14] - base.data.qvel[:7])
        lim = base.joint_limits
        first_limit = base.n_obstacle_barriers + base.n_self_collision_barriers
        speed_h = base.barrier_terms("nominal").h[first_limit + 14:]
        measured = base._sensed_view.data.qvel[:7]
        top = lim.max_speed - lim.speed_margin
        np.testing.assert_allclose(speed_h[1::2], top - measured, atol=1e-12)
        assert info["h"] == base.true_state_terms("true").h[:base.n_obstacle_barriers].min()
        assert info["joint_velocity_error"] == pytest.approx(
            np.abs(measured - base.data.qvel[:7]).max())
    lo, hi = _chi2_band(7 * 200)
    assert lo < (np.array(dqd, dtype=np.float64) ** 2).mean() / sv ** 2 < hi
    assert lo < (np.array(dq, dtype=np.float64) ** 2).mean() / sq ** 2 < hi * 1.01


def test_pushes_act_at_their_rate_and_move_the_arm():
    """10 N for 0.1 s at 2 per second: a push acts in about rate x duration of the steps
    (binomial band over pushes), ``xfrc_applied`` holds it on one link, and the arm moves
    away from where the unpushed arm stays."""
    push = {"force": 10.0, "duration": 0.1, "rate": 2.0}
    env = gym.make(STATIC, push=push, warmup_steps=250)
    still = gym.make(STATIC, warmup_steps=250)
    base = env.unwrapped
    env.reset(seed=3)
    still.reset(seed=3)
    zero = np.zeros(7, dtype=np.float32)
    active, moved = 0, 0.0
    n = 2500
    for _ in range(n):
        info = env.step(zero)[4]
        still.step(zero)
        if info["push_active"]:
            active += 1
            rows = np.flatnonzero(np.abs(base.data.xfrc_applied).sum(axis=1))
            assert len(rows) == 1
            assert np.linalg.norm(base.data.xfrc_applied[rows[0], :3]) == pytest.approx(10.0)
        moved = max(moved, float(np.abs(base.data.qpos - still.unwrapped.data.qpos).max()))
    # each push lasts 25 steps; pushes start in a free step with probability 1 - exp(-2 dt)
    p = -np.expm1(-2.0 * 0.004)
    expected = 25 * p / (1 + 25 * p)  # the share of steps under a push (renewal)
    assert abs(active / n - expected) < 4 * np.sqrt(expected * 25 / n)
    assert moved > 1e-3


def test_pair_covariance_is_the_first_order_propagation():
    """Against central differences of :func:`sphere_barriers` in the obstacle's position,
    velocity and acceleration (``lf = n'(a_s - a_o) + curvature`` with ``a_s = 0``), at
    ordinary and at near-grazing pairs (``v`` almost along ``n``); without a model (``lf =
    0``) only ``h`` and ``h'`` vary."""
    rng = np.random.default_rng(0)
    k = 6
    d = rng.normal(size=(k, 3)) * 0.2
    v = rng.normal(size=(k, 3)) * 0.3
    v[0] = d[0] / np.linalg.norm(d[0]) * 0.5 + 1e-6  # near-grazing
    a_o = rng.normal(size=(k, 3))
    radius = np.full(k, 0.1)

    def quantities(p_o, v_o, acc):  # obstacle state relative to the nominal one
        h, hd, n, curv = sphere_barriers(d - p_o, v - v_o, radius)
        return np.stack([h, hd, curv - np.einsum("ki,ki->k", n, acc)], axis=1)

    jac = np.zeros((k, 3, 9))
    eps = 1e-6
    zero = np.zeros((k, 3))
    for block in range(3):
        for axis in range(3):
            delta = zero.copy()
            delta[:, axis] = eps
            args_up = [zero, zero, a_o]
            args_dn = [zero, zero, a_o]
            args_up[block] = args_up[block] + delta
            args_dn[block] = args_dn[block] - delta
            jac[:, :, 3 * block + axis] = (quantities(*args_up) - quantities(*args_dn)) / (2 * eps)
    per_axis = np.array([[1e-4, 2e-4, 0.0], [2e-4, 1e-2, 1e-3], [0.0, 1e-3, 0.5]])
    full = np.kron(per_axis, np.eye(3))  # [p, v, a] blocks, x y z within each
    expected = jac @ full @ jac.transpose(0, 2, 1)
    dist = np.linalg.norm(d, axis=1)
    n = d / dist[:, None]
    per_pair = np.broadcast_to(per_axis, (k, 3, 3))
    got = pair_covariance(n, dist, v, per_pair, relative_acc=-a_o)  # a_s = 0 here
    scale = np.abs(expected).max(axis=(1, 2))[:, None, None]
    np.testing.assert_allclose(got / scale, expected / scale, atol=1e-7)
    nothing_known = pair_covariance(n, dist, v, per_pair, relative_acc=None)  # lf = 0
    np.testing.assert_array_equal(nothing_known[:, 2], 0.0)
    np.testing.assert_allclose(nothing_known[:, :2, :2] / scale, expected[:, :2, :2] / scale,
                               atol=1e-7)


def test_an_estimate_changes_the_obstacles_not_the_joint_reading():
    """Setting an obstacle estimate within a control period keeps that period's encoder
    reading (one draw per period) and moves only the obstacle terms."""
    env = gym.make(STATIC, velocity_noise=0.05, obstacle_noise=0.01)
    base = env.unwrapped
    env.reset(seed=4)
    env.step(np.zeros(7, dtype=np.float32))
    before = base._sensed_view.data.qvel.copy()
    h_before = base.barrier_terms("nominal").h.copy()
    p = np.array([base._obstacle_states[0][0]]) + 0.02
    base.set_obstacle_estimate(p, np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None] * 1e-4)
    np.testing.assert_array_equal(base._sensed_view.data.qvel, before)
    after = base.barrier_terms("nominal")
    k = base.n_obstacle_barriers
    np.testing.assert_array_equal(after.h[k:], h_before[k:])  # joint limits: same reading
    assert not np.allclose(after.h[:k], h_before[:k])
    assert after.covariance is not None and after.covariance[:k, 0, 0].min() > 0


@pytest.mark.parametrize("env_id", [STATIC, DYNAMIC, "afvsgp_gym/FrankaObstacleRandom-v0",
                                    "afvsgp_gym/FrankaObstacleReach-v0"])
def test_every_franka_id_takes_the_sensing_options(env_id):
    """Each id senses through the camera and the encoders and refuses a bad option; the
    same seed draws the same task with and without sensing."""
    kwargs = {"obstacle_noise": 0.01, "obstacle_rate": 30.0, "obstacle_delay": 0.03,
              "velocity_noise": 0.01, "push": {"force": 5.0, "duration": 0.1, "rate": 1.0}}
    env, exact = gym.make(env_id, **kwargs), gym.make(env_id)
    env.reset(seed=5)
    exact.reset(seed=5)
    np.testing.assert_array_equal(env.unwrapped.data.qpos, exact.unwrapped.data.qpos)
    info = env.step(env.action_space.sample())[4]
    assert info["joint_velocity_error"] > 0 and info["obstacle_error"] > 0
    with pytest.raises(ValueError, match="obstacle_delay"):
        gym.make(env_id, obstacle_delay=-1.0)
