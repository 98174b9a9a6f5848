"""The DH sphere kinematics against MuJoCo's for the gymnasium-robotics Panda, and J' q'
against a finite difference."""

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES
from afvsgp_gym.robots.kinematics import (
    FRANKA_PANDA,
    GYMNASIUM_PANDA,
    DHChain,
    SphereKinematics,
)
from afvsgp_gym.robots.libfranka import check_kinematics
from afvsgp_gym.robots.simulated import SimulatedFranka

EPS = np.finfo(np.float64).eps


@pytest.fixture(scope="module")
def panda():
    model = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    return model, mujoco.MjData(model)


def _states(model, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = model.jnt_range[:7, 0], model.jnt_range[:7, 1]
    for _ in range(n):
        yield rng.uniform(lo, hi), rng.uniform(-2.5, 2.5, 7)


def test_body_frames_are_the_dh_frames(panda):
    model, data = panda
    for q, _ in _states(model, 50, 0):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        rot, org = GYMNASIUM_PANDA.frames(q)
        for i in range(7):
            body = model.body(f"panda0_link{i + 1}").id
            np.testing.assert_allclose(rot[i], data.xmat[body].reshape(3, 3), rtol=0, atol=1e-12)
            np.testing.assert_allclose(org[i], data.xpos[body], rtol=0, atol=1e-12)


def test_spheres_jacobians_and_velocity_product_match_mujoco(panda):
    model, data = panda
    kin = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES)
    jac = np.zeros((3, model.nv))
    jac_dot = np.zeros((3, model.nv))
    for q, qd in _states(model, 200, 1):
        data.qpos[:], data.qvel[:] = q, qd
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_comVel(model, data)
        p, v, J, acc = kin(q, qd)
        for s, sphere in enumerate(PANDA_ARM_SPHERES):
            body = model.body(sphere.body).id
            centre = data.xmat[body].reshape(3, 3) @ np.array(sphere.offset) + data.xpos[body]
            mujoco.mj_jac(model, data, jac, None, centre, body)
            mujoco.mj_jacDot(model, data, jac_dot, None, centre, body)
            np.testing.assert_allclose(p[s], centre, rtol=0, atol=1e-9)
            np.testing.assert_allclose(J[s], jac, rtol=0, atol=1e-9)
            np.testing.assert_allclose(v[s], jac @ qd, rtol=0, atol=1e-9)
            np.testing.assert_allclose(acc[s], jac_dot @ qd, rtol=0, atol=1e-9)


def test_velocity_product_is_the_derivative_of_the_jacobian_along_the_motion(panda):
    """``J' q' = d/dt [J(q + t q') q']`` at t = 0, by a central difference with step t.
    Its error is at most ``t^2 / 6 max|d^3/dt^3 J q'|`` (truncation) plus ``2 eps |J q'| / t``
    (rounding of the two evaluations, amplified by 1/(2t)); each time derivative of a point on
    a chain of rotations brings at most a factor ``sum|q'|`` (every joint rate) times the reach
    ``R`` (1.3 m bounds every point's distance to every joint axis), so the bound is
    ``t^2 / 6 R w^4 + 2 eps R w / t`` with ``w = sum|q'|``."""
    model, _ = panda
    kin = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES)
    reach, t = 1.3, 1e-4
    for q, qd in _states(model, 50, 2):
        w = np.abs(qd).sum()
        tol = t * t / 6.0 * reach * w**4 + 2.0 * EPS * reach * w / t
        _, _, _, acc = kin(q, qd)
        up = kin(q + t * qd, qd)[2] @ qd
        down = kin(q - t * qd, qd)[2] @ qd
        fd = (up - down) / (2.0 * t)
        assert np.abs(fd - acc).max() <= tol


def test_frankas_table_differs_from_the_simulated_panda_by_its_rounded_angles(panda):
    """With the joint-zero shift, Franka's table puts the spheres where the gymnasium-robotics
    model does up to its rounded pi/2 (1.57): below a millimetre."""
    model, _ = panda
    sim = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES)
    real = SphereKinematics.from_spheres(FRANKA_PANDA, PANDA_ARM_SPHERES)
    worst = 0.0
    for q, _ in _states(model, 100, 3):
        diff = real.positions(q + GYMNASIUM_PANDA.theta_offset) - sim.positions(q)
        worst = max(worst, float(np.linalg.norm(diff, axis=1).max()))
    assert 1e-5 < worst < 1e-3


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="alpha"):
        DHChain(a=np.zeros(7), d=np.zeros(7), alpha=np.zeros(6))
    with pytest.raises(ValueError, match="links"):
        SphereKinematics(FRANKA_PANDA, [0], [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="offsets"):
        SphereKinematics(FRANKA_PANDA, [1, 2], [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="body"):
        SphereKinematics.from_spheres(FRANKA_PANDA, [PANDA_ARM_SPHERES[0].__class__(
            "panda0_hand", (0.0, 0.0, 0.0), 0.1)])


def test_the_stand_ins_flange_and_jacobian_check_the_kinematics():
    """``check_kinematics`` (the bridge's check at the start) against the stand-in's own
    ``O_T_EE``, ``F_T_EE`` and ``Model.zero_jacobian`` (MuJoCo's): the simulated model's
    table agrees to rounding, Franka's table at the simulated angles does not."""
    robot = SimulatedFranka(realtime=False)
    model = robot.load_model()
    rng = np.random.default_rng(7)
    for _ in range(20):
        lim = robot.joint_limits
        robot.set_state(rng.uniform(lim.lower, lim.upper), np.zeros(7))
        state = robot.read_once()
        err = check_kinematics(state, model, GYMNASIUM_PANDA)
        assert max(err.values()) < 1e-9
    with pytest.raises(RuntimeError, match="'franka' are not the robot's"):
        check_kinematics(state, model, FRANKA_PANDA)
