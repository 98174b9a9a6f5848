"""FrankaObstacleReachEnv: exact barrier terms for the velocity action, inner loop, task
geometry, warm-up clearance, reward and API."""

import itertools

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.agents import NominalController
from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.reach import FrankaObstacleReachEnv
from afvsgp_gym.envs.task_velocity import TaskVelocityLoop, compose_affine

ID = "afvsgp_gym/FrankaObstacleReach-v0"


@pytest.fixture(scope="module", params=["arm", "ee"])
def fd_env(request):
    """Tiny physics step, one step per action: the torque is held over the step, so the
    h'' split is exact up to O(dt)."""
    env = FrankaObstacleReachEnv(physics_dt=1e-4, frame_skip=1, safety_spheres=request.param)
    env.reset(seed=3)
    return env


def _probe(env, q, qd, u):
    env.set_state(q, qd)
    env.step(u)
    return env.barrier_terms("true").derivatives.copy()


def test_true_terms_match_finite_differences(fd_env):
    """Every (sphere, obstacle) pair: h' from h, lf from h' at u = 0, lg per unit of each
    velocity-command axis, through the inner loop's torques."""
    env = fd_env
    rng = np.random.default_rng(1)
    q = fm.Q_HOME + rng.uniform(-0.2, 0.2, 7)
    qd = rng.uniform(-0.5, 0.5, 7)
    env.set_state(q, qd)
    t0 = env.barrier_terms("true")
    d_now = t0.derivatives.copy()
    lf, lg = t0.lf.copy(), t0.lg.copy()
    assert lg.shape == (env.n_barriers, 3)
    dt = env.dt
    rows, top = np.arange(env.n_barriers), env.barrier_layout.relative_degree - 1
    two = np.flatnonzero(top == 1)  # h' from h where h' is measured (relative degree 2)
    d0 = _probe(env, q, qd, np.zeros(3))
    assert not env._saturated
    np.testing.assert_allclose((d0[two, 0] - d_now[two, 0]) / dt, d0[two, 1],
                               rtol=1e-3, atol=1e-4 * np.abs(d_now[two, 1]).max())
    lf_fd = (d0[rows, top] - d_now[rows, top]) / dt
    lg_fd = np.stack([(_probe(env, q, qd, np.eye(3)[i])[rows, top] - d0[rows, top]) / dt
                      for i in range(3)], axis=1)
    u = np.array([0.3, -0.7, 0.5])  # a combined command: the highest derivative is affine in u
    h2 = (_probe(env, q, qd, u)[rows, top] - d_now[rows, top]) / dt
    # obstacle pairs (m) and joint limits (rad), each against its own scale
    for group in (np.arange(env.n_obstacle_barriers), np.arange(env.n_obstacle_barriers,
                                                                  env.n_barriers)):
        np.testing.assert_allclose(lf_fd[group], lf[group], rtol=2e-2,
                                   atol=2e-2 * np.abs(lf[group]).max())
        np.testing.assert_allclose(lg_fd[group], lg[group], rtol=2e-2,
                                   atol=2e-2 * np.abs(lg[group]).max())
        assert np.abs(lg[group]).max() > 1.0  # the action matters: the check is not vacuous
        np.testing.assert_allclose(h2[group], (lf + lg @ u)[group], rtol=2e-2,
                                   atol=2e-2 * np.abs(lg[group]).max())


def test_inner_loop_torque_formula():
    """tau = A u + c against the loop's formula written out, at a random state."""
    env = FrankaObstacleReachEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(2)
    q = fm.Q_HOME + rng.uniform(-0.3, 0.3, 7)
    qd = rng.uniform(-1, 1, 7)
    env.set_state(q, qd)
    loop = env.loop
    m, d = env.model, mujoco.MjData(env.model)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    jac = np.zeros((3, 7))
    mujoco.mj_jacSite(m, d, jac, None, m.site("end_effector").id)
    ja = jac[:, :4]
    # J_a^+ = (J_a' J_a + lambda I)^-1 J_a' is the same matrix as J_a' (J_a J_a' + lambda I)^-1
    lam = loop.regularization
    pinv = np.linalg.solve(ja.T @ ja + lam * np.eye(4), ja.T)
    null = np.eye(4) - pinv @ ja
    u = rng.uniform(-1, 1, 3)
    f = loop.damping * (loop.max_speed * u - jac @ qd)
    err = env.q_home - q
    tau = np.empty(7)
    tau[:4] = ja.T @ f + null.T @ (loop.posture_stiffness * err[:4] - loop.posture_damping * qd[:4])
    tau[4:] = loop.wrist_stiffness * err[4:] - loop.wrist_damping * qd[4:]
    np.testing.assert_allclose(env._A @ u + env._c, tau, rtol=1e-9, atol=1e-9 * np.abs(tau).max())


def test_compose_affine_is_the_torque_chain_rule():
    rng = np.random.default_rng(0)
    lf_t, lg_t = rng.normal(size=5), rng.normal(size=(5, 7))
    A, c = rng.normal(size=(7, 3)), rng.normal(size=7)
    lf, lg = compose_affine(lf_t, lg_t, A, c)
    for u in rng.normal(size=(4, 3)):
        np.testing.assert_allclose(lf + lg @ u, lf_t + lg_t @ (A @ u + c), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("nominal_model", ["kinematic", "perturbed", "exact"])
def test_nominal_models_and_delta_b_true(nominal_model):
    env = FrankaObstacleReachEnv(nominal_model=nominal_model)
    env.reset(seed=1)
    env.step(np.array([0.5, 0.5, -0.5]))
    true, nom = env.barrier_terms("true"), env.barrier_terms("nominal")
    u = np.array([-0.2, 0.9, 0.1])
    _, _, _, _, info = env.step(u)
    want = (true.lf - nom.lf) + (true.lg - nom.lg) @ u
    np.testing.assert_allclose(info["delta_b_true"], want, rtol=1e-12, atol=1e-12)
    if nominal_model == "kinematic":
        assert np.all(nom.lg == 0)  # the dynamics behind the inner loop are unknown
    if nominal_model == "exact":
        np.testing.assert_allclose(nom.lf, true.lf, rtol=1e-12, atol=1e-12)
    if nominal_model == "perturbed":  # the catalogue model: the action gain nearly right
        assert np.corrcoef(nom.lg.ravel(), true.lg.ravel())[0, 1] > 0.9


@pytest.mark.parametrize("seed", range(6))
def test_task_geometry(seed):
    """Goal in range; every obstacle near the straight path, clear of the start (by
    start_clearance), of the goal and of the others."""
    env = FrankaObstacleReachEnv(n_obstacles=2 if seed % 2 else 1)
    env.reset(seed=seed)
    p0, g = env._ee[0], env.goal
    dist = np.linalg.norm(g - p0)
    assert env.GOAL_DISTANCE[0] <= dist <= env.GOAL_DISTANCE[1]
    axis = (g - p0) / dist
    h0 = env.barrier_terms("true").h[:env.n_obstacle_barriers]  # the self pairs are closer
    assert h0.min() >= env.start_clearance
    for k, ob in enumerate(env.obstacles):
        rel = ob.position - p0
        along = rel @ axis
        assert 0 <= along <= dist
        assert np.linalg.norm(rel - along * axis) <= ob.radius + (0.2 if k else 0.03) + 1e-12
        assert np.linalg.norm(g - ob.position) - ob.radius >= env.GOAL_CLEARANCE
        for other in env.obstacles[k + 1:]:
            gap = np.linalg.norm(other.position - ob.position) - other.radius - ob.radius
            assert gap >= env.OBSTACLE_GAP
        gid = env._obstacle_geoms[k]
        assert env.model.geom_size[gid, 0] == ob.radius
    assert env.observation_space.shape == (26 + 4 * env.n_obstacles,)


def test_straight_path_is_blocked_and_the_oracle_filter_clears_it():
    """The obstacle is in the way: the straight-line command has cost in most episodes
    without a filter, none behind the oracle filter."""
    from afvsgp_gym.wrappers import SafetyFilter

    hits = 0
    for seed in range(6):
        for filtered in (False, True):
            env = gym.make(ID)
            if filtered:
                env = SafetyFilter(env, learner="oracle")
            policy = NominalController(env)
            obs, _ = env.reset(seed=seed)
            cost = 0
            for _ in range(1250):
                obs, _, term, trunc, info = env.step(policy(obs))
                cost += info["cost"] > 0
                if term or trunc:
                    break
            if filtered:
                assert cost == 0
            else:
                hits += cost > 0
    assert hits >= 4


@pytest.mark.parametrize("seed", range(2))
def test_no_sphere_reaches_an_obstacle_during_the_filter_warmup(seed):
    """Whatever the commands, the filter's warm-up steps (nominal "zero": nothing certified)
    keep every barrier positive. Constant commands along the 26 axis and diagonal directions
    (the diagonals are the fastest) and random ones, for as many steps as SafetyFilter's
    warm-up takes on this env."""
    from afvsgp_gym.wrappers import SafetyFilter

    env = FrankaObstacleReachEnv()
    n_warm = SafetyFilter(env, learner="afvsgp").controller.config.warmup_samples + 1
    assert n_warm <= env.warmup_steps
    rng = np.random.default_rng(seed)
    dirs = [np.array(d, float) for d in itertools.product([-1, 0, 1], repeat=3) if any(d)]
    dirs += [None] * 4
    worst = np.inf
    for d in dirs:
        env.reset(seed=seed)
        for _ in range(n_warm):
            _, _, _, _, info = env.step(rng.uniform(-1, 1, 3) if d is None else d)
            worst = min(worst, info["h"])
            assert not info["torque_saturated"]
    assert worst > 0.0
    assert worst < env.start_clearance  # the commands moved the arm towards the obstacles


def test_reward_terms_success_and_termination():
    env = gym.make(ID)
    obs, info = env.reset(seed=4)
    assert info["success"] is False
    base = env.unwrapped
    policy = NominalController(env)
    d0 = info["tracking_error"]
    progress = 0.0
    for _ in range(1250):
        obs, reward, term, trunc, info = env.step(policy(obs))
        parts = (info["reward_progress"] + info["reward_time"] + info["reward_ctrl"]
                 + info["reward_cost"] + info["reward_success"])
        assert reward == parts
        assert info["reward_cost"] == -base.cost_weight * info["cost"]
        progress += info["reward_progress"]
        if term or trunc:
            break
    # the progress terms telescope to the approach
    np.testing.assert_allclose(progress, base.progress_weight * (d0 - info["tracking_error"]),
                               rtol=1e-9)
    # straight at the goal without a filter: reaches it (the obstacle is not physical)
    assert term and info["success"] and info["tracking_error"] < base.goal_tolerance
    assert info["reward_success"] == base.success_bonus
    np.testing.assert_allclose(obs[23:26], base.goal - base._ee[0], rtol=1e-6, atol=1e-6)


def test_checkers_and_bad_arguments():
    from gymnasium.utils.env_checker import check_env

    check_env(gym.make(ID).unwrapped, skip_render_check=True)
    env = FrankaObstacleReachEnv()
    assert env.action_space.shape == (3,) and env.action_repeat == 10
    with pytest.raises(ValueError, match="n_obstacles"):
        FrankaObstacleReachEnv(n_obstacles=0)
    with pytest.raises(ValueError, match="max_speed"):
        FrankaObstacleReachEnv(max_speed=-1.0)
    with pytest.raises(TypeError, match="unknown argument"):
        FrankaObstacleReachEnv(scenario="static")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(7))


def test_sb3_check_env():
    pytest.importorskip("stable_baselines3", reason="needs the rl extra")
    from stable_baselines3.common.env_checker import check_env

    check_env(gym.make(ID))


def test_backup_is_a_zero_velocity_command():
    env = FrankaObstacleReachEnv()
    env.reset(seed=0)
    for _ in range(50):
        env.step(np.array([1.0, 1.0, 0.0]))
    speed = np.linalg.norm(env._ee[1])
    for _ in range(25):  # 0.1 s
        env.step(env.backup_action())
    assert np.linalg.norm(env._ee[1]) < 0.5 * speed
    assert TaskVelocityLoop().max_speed == env.loop.max_speed
