"""The robot's own limits: JointLimits against hand-written formulas, the Franka env's limit
barriers against finite differences of the nominal model, the violation checks, bad input."""

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.joint_limits import (
    FRANKA_MAX_ACCELERATION,
    FRANKA_MAX_SPEED,
    JointLimits,
)

LOWER = np.array([-2.0, -1.0, -3.0])
UPPER = np.array([2.0, 1.5, -0.5])
SPEED = np.array([2.0, 1.0, 3.0])


def test_derivatives_features_and_terms_follow_the_table():
    lim = JointLimits(LOWER, UPPER, SPEED, range_margin=0.1, speed_margin=0.2)
    q, qd = np.array([0.5, -0.3, -1.0]), np.array([1.5, -0.25, 0.7])
    d = lim.derivatives(q, qd)
    assert d.shape == (12, 2) and lim.n_barriers == 12
    for j in range(3):  # one joint at a time, written out
        np.testing.assert_array_equal(d[2 * j], [q[j] - LOWER[j] - 0.1, qd[j]])
        np.testing.assert_array_equal(d[2 * j + 1], [UPPER[j] - 0.1 - q[j], -qd[j]])
        np.testing.assert_array_equal(d[6 + 2 * j], [qd[j] + SPEED[j] - 0.2, 0.0])
        np.testing.assert_array_equal(d[6 + 2 * j + 1], [SPEED[j] - 0.2 - qd[j], 0.0])
    np.testing.assert_array_equal(lim.relative_degree, [2] * 6 + [1] * 6)
    xi = lim.features(q, qd, 10)
    np.testing.assert_array_equal(xi, np.tile(np.r_[q, qd, 0, 0, 0, 0], (12, 1)))
    acc, gain = np.array([3.0, -4.0, 5.0]), np.arange(6.0).reshape(3, 2)
    lf, lg = lim.terms(acc, gain)
    for j in range(3):  # h^(r) = +-q''_j: lower range and lower speed +, upper ones -
        for row, sign in ((2 * j, 1), (2 * j + 1, -1), (6 + 2 * j, 1), (6 + 2 * j + 1, -1)):
            assert lf[row] == sign * acc[j]
            np.testing.assert_array_equal(lg[row], sign * gain[j])
    assert lim.names()[:2] == ("joint1/range_min", "joint1/range_max")
    assert lim.names()[6:8] == ("joint1/speed_min", "joint1/speed_max")


def test_violation_at_the_stop_and_above_the_speed_not_at_the_margin():
    lim = JointLimits(LOWER, UPPER, SPEED, range_margin=0.1, speed_margin=0.2,
                      max_acceleration=np.array([10.0, 10.0, 10.0]), max_torque_rate=1000.0)
    q, qd = np.array([0.0, 0.0, -1.0]), np.zeros(3)
    assert not lim.violation(q, qd)
    assert not lim.violation(np.array([-1.95, 1.45, -2.95]), np.array([1.9, -0.9, 2.9]))  # inside
    assert lim.violation(np.array([-2.0, 0.0, -1.0]), qd)  # at the lower stop
    assert lim.violation(np.array([0.0, 1.5, -1.0]), qd)  # at the upper stop
    assert lim.violation(q, np.array([0.0, -1.0001, 0.0]))  # above the speed
    assert lim.violation(q, qd, qdd=np.array([0.0, 0.0, -10.5]))
    assert not lim.violation(q, qd, qdd=np.array([0.0, 0.0, -9.5]))
    assert lim.violation(q, qd, torque_rate=np.array([1001.0, 0.0, 0.0]))
    plain = JointLimits(LOWER, UPPER, SPEED)  # the optional checks off
    assert not plain.violation(q, qd, qdd=np.full(3, 1e3), torque_rate=np.full(3, 1e6))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"upper": np.array([2.0, -1.0, -0.5])}, "joint 2: lower"),
        ({"lower": np.array([-2.0, np.nan, -3.0])}, "lower of joint 2"),
        ({"max_speed": np.array([2.0, 0.0, 3.0])}, "max_speed of joint 2"),
        ({"max_speed": np.array([2.0, 1.0, -3.0])}, "max_speed of joint 3"),
        ({"range_margin": 0.3}, "range_margin"),  # above half of joint 3's range (below)
        ({"speed_margin": 1.0}, "speed_margin"),
        ({"speed_margin": -0.1}, "speed_margin"),
        ({"max_acceleration": np.array([1.0, np.inf, 1.0])}, "max_acceleration of joint 2"),
        ({"max_torque_rate": 0.0}, "max_torque_rate"),
    ],
)
def test_inconsistent_limits_are_refused_naming_the_joint(kwargs, match):
    args = {"lower": LOWER, "upper": UPPER, "max_speed": SPEED, "range_margin": 0.0}
    if "range_margin" in kwargs:
        args["upper"] = np.array([2.0, 1.5, -2.5])  # joint 3's range is 0.5 rad: half is 0.25
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        JointLimits(**args)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"range_margin": -0.1}, "range_margin"), ({"speed_margin": np.nan}, "speed_margin"),
     ({"speed_margin": 3.0}, "speed_margin"), ({"brake_frequency": 0.0}, "brake_frequency"),
     ({"brake_hold_memory": -0.1}, "brake_hold_memory"),
     ({"brake_hold_slack": -0.01}, "brake_hold_slack")],
)
def test_franka_refuses_bad_limit_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FrankaObstacleEnv("static", **kwargs)


def test_franka_limits_are_the_models_ranges_and_the_datasheet_speeds():
    env = FrankaObstacleEnv("static", self_collision=False)  # 21 pairs, then the limits
    lim = env.joint_limits
    np.testing.assert_array_equal(lim.lower, env.model.jnt_range[:7, 0])
    np.testing.assert_array_equal(lim.upper, env.model.jnt_range[:7, 1])
    np.testing.assert_array_equal(lim.max_speed, [2.175] * 4 + [2.61] * 3)
    assert lim.max_acceleration is None and lim.max_torque_rate is None
    # joints 4 and 6 of the gymnasium-robotics model differ from the datasheet (-0.0698 and
    # 3.7525 there): the model's ranges are the ones its joint stops enforce
    assert lim.upper[3] == pytest.approx(-0.4) and lim.upper[5] == pytest.approx(2.1127)
    layout = env.barrier_layout
    assert layout.n_learners == 21 + 7 and np.array_equal(layout.group, [0] * 21 + [1] * 7)
    np.testing.assert_array_equal(layout.learner[21:25], [21, 21, 22, 22])
    np.testing.assert_array_equal(layout.sign[21:25], [1, -1, 1, -1])
    off = FrankaObstacleEnv("static", limit_barriers=False, self_collision=False)
    assert off.n_barriers == off.n_obstacle_barriers == 21 and off.barrier_layout.is_uniform


def test_info_reports_limit_violations_as_cost():
    env = FrankaObstacleEnv("static", warmup_steps=0)
    env.reset(seed=0)
    q = fm.Q_HOME.copy()
    env.set_state(q, np.r_[2.3, np.zeros(6)])  # joint 1 above 2.175 rad/s, far from obstacles
    info = env._safety_info()
    assert info["limit_violation"] and info["cost"] == 1.0 and info["h"] > 0 and not info[
        "collision"]
    q[3] = env.joint_limits.upper[3]  # joint 4 at its upper stop, at rest
    env.set_state(q, np.zeros(7))
    info = env._safety_info()
    assert info["limit_violation"] and info["cost"] == 1.0
    env.set_state(fm.Q_HOME, np.zeros(7))
    assert not env._safety_info()["limit_violation"]


def test_optional_acceleration_and_torque_rate_checks():
    """Full torque on joint 1 from rest: above 15 rad/s^2 and above 1000 Nm/s of torque rate
    (87 Nm in 4 ms), counted only when the checks are on."""
    for check_acceleration, check_torque_rate in ((True, False), (False, True), (False, False)):
        env = FrankaObstacleEnv("static", warmup_steps=0, check_acceleration=check_acceleration,
                                check_torque_rate=check_torque_rate)
        env.reset(seed=0)
        _, _, _, _, info = env.step(np.r_[1.0, np.zeros(6)])
        assert info["limit_violation"] == (check_acceleration or check_torque_rate)
        if check_acceleration:
            assert env.joint_limits.max_acceleration[0] == FRANKA_MAX_ACCELERATION[0] == 15.0


def test_perturbed_limit_terms_match_finite_differences_of_the_nominal_model():
    """The "perturbed" prior's joint-limit terms are the catalogue model's joint
    accelerations: simulated in that model with a tiny step (forward differences, O(dt))."""
    env = FrankaObstacleEnv("static", nominal_model="perturbed", physics_dt=1e-4,
                            frame_skip=1, warmup_steps=0)
    env.reset(seed=0)
    rng = np.random.default_rng(5)
    q, qd = fm.Q_HOME + rng.uniform(-0.3, 0.3, 7), rng.uniform(-1.0, 1.0, 7)
    env.set_state(q, qd)
    terms = env.barrier_terms("nominal")
    k = env.n_obstacle_barriers + env.n_self_collision_barriers  # the first limit barrier
    m = env.nominal_mj_model
    data = mujoco.MjData(m)

    def qdd(u):
        data.qpos[:] = q
        data.qvel[:] = qd
        data.ctrl[:] = u
        mujoco.mj_step(m, data)
        return (data.qvel[:7] - qd) / m.opt.timestep

    acc0 = qdd(np.zeros(7))
    gains = np.stack([qdd(np.eye(7)[i]) - acc0 for i in range(7)], axis=1)
    lim = env.joint_limits
    scale_lf, scale_lg = np.abs(acc0).max(), np.abs(gains).max()
    assert scale_lg > 10.0  # the action matters
    for row in range(28):
        j, sign = lim.joint[row], lim.sign[row]
        np.testing.assert_allclose(terms.lf[k + row], sign * acc0[j], atol=2e-2 * scale_lf)
        np.testing.assert_allclose(terms.lg[k + row], sign * gains[j], atol=2e-2 * scale_lg)
    true = env.barrier_terms("true")  # the plant differs: payload, masses, damping
    assert np.abs(true.lf[k:] - terms.lf[k:]).max() > 0.1 * scale_lf


def test_franka_speed_constants_are_the_datasheet():
    np.testing.assert_array_equal(FRANKA_MAX_SPEED, [2.175] * 4 + [2.61] * 3)
