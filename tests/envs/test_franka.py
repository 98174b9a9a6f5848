"""FrankaObstacleEnv: barrier ground truth vs finite differences, plant, scenarios, API."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.agents import NominalController
from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.franka import FrankaObstacleEnv

IDS = {
    "static": "afvsgp_gym/FrankaObstacleStatic-v0",
    "dynamic": "afvsgp_gym/FrankaObstacleDynamic-v0",
    "random": "afvsgp_gym/FrankaObstacleRandom-v0",
}


@pytest.fixture(scope="module")
def fd_env():
    """Tiny physics step, one step per action, no friction: h'' split is exact."""
    env = FrankaObstacleEnv("dynamic", physics_dt=1e-4, frame_skip=1, warmup_steps=0)
    env.reset(seed=0)
    return env


def _probe(env, q, qd, k, u):
    env.set_state(q, qd)
    env.set_time_step(k)
    env.step(u)
    return env.barrier_terms("true")[0].derivatives


def test_true_terms_match_finite_differences(fd_env):
    env = fd_env
    rng = np.random.default_rng(1)
    q = fm.Q_HOME + rng.uniform(-0.2, 0.2, 7)
    qd = rng.uniform(-0.5, 0.5, 7)
    ob = env.obstacles[0]
    k = int(0.3 * ob.duration / env.dt)  # obstacle accelerating
    env.set_state(q, qd)
    env.set_time_step(k)
    assert np.linalg.norm(env._obs_states[0][2]) > 1e-3
    t0 = env.barrier_terms("true")[0]
    dt = env.dt
    d0 = _probe(env, q, qd, k, np.zeros(7))
    np.testing.assert_allclose((d0[0] - t0.derivatives[0]) / dt, t0.derivatives[1], rtol=1e-3)
    lf_fd = (d0[1] - t0.derivatives[1]) / dt
    np.testing.assert_allclose(lf_fd, t0.lf, rtol=2e-2, atol=2e-2)
    lg_fd = np.array([(_probe(env, q, qd, k, np.eye(7)[i])[1] - d0[1]) / dt for i in range(7)])
    np.testing.assert_allclose(lg_fd, t0.lg, rtol=2e-2, atol=2e-2 * np.abs(t0.lg).max())
    assert np.abs(t0.lg).max() > 1.0  # the action matters: the check is not vacuous


def test_features_and_derivatives(fd_env):
    env = fd_env
    env.set_state(fm.Q_HOME, np.full(7, 0.1))
    t = env.barrier_terms("true")[0]
    m, d = env.model, env.data
    jac = np.zeros((3, 7))
    mujoco.mj_jacSite(m, d, jac, None, env._site)
    p, v = d.site_xpos[env._site], jac @ d.qvel
    po, vo, _ = env._obs_states[0]
    np.testing.assert_allclose(t.xi, np.r_[d.qpos, d.qvel, p - po, v - vo])
    assert env.feature_dim == t.xi.shape[0] == 20
    dist = np.linalg.norm(p - po)
    np.testing.assert_allclose(t.derivatives[0], dist - env.obstacles[0].radius - env.ee_radius)
    np.testing.assert_allclose(t.derivatives[1], (p - po) @ (v - vo) / dist)


@pytest.mark.parametrize("nominal_model", ["zero", "kinematic", "perturbed", "exact"])
def test_delta_b_true_is_true_minus_nominal(nominal_model):
    env = FrankaObstacleEnv("dynamic", nominal_model=nominal_model, warmup_steps=0)
    env.reset(seed=0)
    env.set_state(fm.Q_HOME, np.linspace(-0.3, 0.3, 7))
    env.set_time_step(200)
    u = np.linspace(-0.5, 0.5, 7).astype(np.float32)
    tt, tn = env.barrier_terms("true")[0], env.barrier_terms("nominal")[0]
    np.testing.assert_allclose(tn.derivatives, tt.derivatives)
    _, _, _, _, info = env.step(u)
    expected = (tt.lf + tt.lg @ u) - (tn.lf + tn.lg @ u)
    np.testing.assert_allclose(info["delta_b_true"], [expected], rtol=1e-10)
    if nominal_model == "exact":
        assert abs(info["delta_b_true"][0]) < 1e-9
    else:
        assert abs(info["delta_b_true"][0]) > 1e-3  # a real mismatch to learn
    if nominal_model == "zero":
        assert tn.lf == 0.0 and not np.any(tn.lg)
    if nominal_model == "kinematic":
        assert not np.any(tn.lg) and tn.lf != 0.0


def test_gravity_compensation_and_torque_scaling():
    # catalogue plant: the robot's compensation cancels gravity exactly
    env = FrankaObstacleEnv(payload_mass=0.0, mass_scale=1.0, damping=0.0, armature=0.0)
    env.reset(seed=0)
    env.set_state(fm.Q_HOME, np.zeros(7))
    np.testing.assert_allclose(env.data.qacc, 0.0, atol=1e-8)
    # true plant: scaled links are compensated only up to their nominal weight
    env = FrankaObstacleEnv(mass_scale=(0.9, 1.3), plant_seed=3)
    m = env.model
    for k, name in enumerate(fm.ARM_BODIES):
        b = m.body(name)
        np.testing.assert_allclose(m.body_gravcomp[b.id], 1.0 / env.plant.mass_scale[k])
        np.testing.assert_allclose(
            b.mass, fm.catalogue_inertials()[name][0] * env.plant.mass_scale[k]
        )
    assert m.body_gravcomp[m.body("payload").id] == 0.0 and m.body("payload").mass == 1.0
    env.reset(seed=0)
    env.set_state(fm.Q_HOME, np.zeros(7))
    assert np.abs(env.data.qacc).max() > 0.1  # residual gravity
    u = np.array([1.0, -1.0, 0.5, 0.0, 1.0, -1.0, 0.25])
    env.data.ctrl[:] = u
    mujoco.mj_forward(m, env.data)
    np.testing.assert_allclose(env.data.qfrc_actuator, u * fm.TAU_MAX)
    np.testing.assert_array_equal(m.actuator_gear[:, 0], [87, 87, 87, 87, 12, 12, 12])


def _run(env, steps, seed=0, oracle_margin=None):
    obs, _ = env.reset(seed=seed)
    policy = NominalController(env)
    base = env.unwrapped
    lo, hi = env.action_space.low.astype(float), env.action_space.high.astype(float)
    hs, obs_log = [], [obs]
    base.collisions = 0
    for _ in range(steps):
        u = policy(obs).astype(np.float64)
        assert np.all(u >= lo) and np.all(u <= hi)
        if oracle_margin is not None:
            u = _oracle_filter(base, u, lo, hi, oracle_margin)
        obs, _, term, trunc, info = env.step(u)
        hs.append(info["h"])
        base.collisions += info["collision"]
        obs_log.append(obs)
        if term or trunc:
            break
    return np.array(hs), np.array(obs_log)


def _oracle_filter(base, u_nom, lo, hi, margin, k1=20.0, k0=100.0):
    """Exact-model HOCBF-QP for one obstacle (projection by bisection on the multiplier)."""
    t = base.barrier_terms("true")[0]
    h, hd = t.derivatives
    a = t.lf + k1 * hd + k0 * (h - margin)

    def g(lam):
        return a + t.lg @ np.clip(u_nom + lam * t.lg, lo, hi)

    if g(0.0) >= 0:
        return u_nom
    lam_lo, lam_hi = 0.0, 1.0
    while g(lam_hi) < 0 and lam_hi < 1e9:
        lam_hi *= 2
    for _ in range(50):
        mid = 0.5 * (lam_lo + lam_hi)
        lam_lo, lam_hi = (mid, lam_hi) if g(mid) < 0 else (lam_lo, mid)
    return np.clip(u_nom + lam_hi * t.lg, lo, hi)


@pytest.mark.parametrize(("scenario", "seed"), [("static", 0), ("dynamic", 0), ("random", 1)])
def test_warmup_clear_then_obstacle_in_the_way(scenario, seed):
    env = gym.make(IDS[scenario])
    hs, _ = _run(env, 4000, seed=seed)
    warm = env.unwrapped.warmup_steps
    assert warm >= 250 and env.unwrapped.dt == pytest.approx(0.004)
    assert hs[:warm].min() > 0.04
    assert hs.min() < -0.02  # the unfiltered tracker enters the unsafe set
    assert env.unwrapped.collisions > 0


@pytest.mark.parametrize(("scenario", "seed"), [("static", 0), ("dynamic", 0), ("random", 2)])
def test_solvable_with_exact_model(scenario, seed):
    """With the true barrier terms a CBF-QP keeps h >= 0 (2 mm sampling margin), no arm hits."""
    env = gym.make(IDS[scenario], nominal_model="exact")
    hs, _ = _run(env, 4000, seed=seed, oracle_margin=0.002)
    assert len(hs) == 4000 and hs.min() >= 0.0
    assert env.unwrapped.collisions == 0


def test_determinism_under_seed():
    _, a = _run(gym.make(IDS["random"]), 300, seed=5)
    _, b = _run(gym.make(IDS["random"]), 300, seed=5)
    _, c = _run(gym.make(IDS["random"]), 300, seed=6)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_dynamic_obstacle_trajectory():
    env = gym.make(IDS["dynamic"])
    _, obs = _run(env, 4000)
    base = env.unwrapped
    pos, vel = obs[:, 20:23], obs[:, 23:26]
    warm = base.warmup_steps
    assert np.abs(pos[: warm + 1] - pos[0]).max() < 1e-6  # at rest during warm-up
    np.testing.assert_allclose(pos[-1], base.obstacles[0].position, atol=1e-6)
    speed = np.linalg.norm(vel, axis=1)
    np.testing.assert_allclose(speed.max(), base.obstacle_speed, rtol=1e-3)
    np.testing.assert_allclose(
        np.diff(pos, axis=0) / base.dt, 0.5 * (vel[1:] + vel[:-1]), atol=2e-4
    )


def test_info_reward_and_spaces():
    env = gym.make(IDS["static"])
    obs, info = env.reset(seed=0)
    assert obs.shape == (35,) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    assert env.spec.max_episode_steps * env.unwrapped.dt >= 16.0
    _, r, _, _, info = env.step(env.action_space.sample())
    assert r == info["reward_tracking"] + info["reward_ctrl"]
    for key in ("cost", "h", "h_per_obstacle", "collision", "delta_b_true", "unstable"):
        assert key in info
    base = env.unwrapped
    assert base.relative_degree == 2 and base.n_obstacles == 1
    assert base.metadata["render_fps"] == round(1 / base.dt) == 250
    terms = base.barrier_terms()
    assert len(terms) == 1 and terms[0].lg.shape == (7,) and terms[0].derivatives.shape == (2,)


def test_bad_input_never_reaches_mujoco():
    env = gym.make(IDS["static"])
    env.reset(seed=0)
    d = env.unwrapped.data
    qpos, qvel, t = d.qpos.copy(), d.qvel.copy(), d.time
    for bad in ([np.nan] * 7, [np.inf] + [0.0] * 6, np.zeros(6), np.zeros((7, 1))):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    np.testing.assert_array_equal(d.qpos, qpos)
    np.testing.assert_array_equal(d.qvel, qvel)
    assert d.time == t
    with pytest.raises(ValueError, match="static"):
        gym.make("afvsgp_gym/FrankaObstacleStatic-v0", scenario="nope")
    with pytest.raises(TypeError, match="payload_mass"):
        gym.make(IDS["static"], payload=1.0)
    for kwargs, name in (
        ({"payload_mass": -1.0}, "payload_mass"),
        ({"physics_dt": "x"}, "physics_dt"),
        ({"mass_scale": (1.0, 2.0, 3.0)}, "mass_scale"),
        ({"nominal_model": "oracle"}, "nominal_model"),
        ({"frame_skip": 0}, "frame_skip"),
    ):
        with pytest.raises(ValueError, match=name):
            FrankaObstacleEnv(**kwargs)


def test_out_of_range_actions_are_clipped():
    e1, e2 = gym.make(IDS["static"]), gym.make(IDS["static"])
    e1.reset(seed=0)
    e2.reset(seed=0)
    u = np.array([3, -3, 0.5, 2, -2, 1, 0])
    np.testing.assert_array_equal(e1.step(u)[0], e2.step(np.clip(u, -1, 1))[0])


def test_unstable_simulation_ends_episode():
    env = gym.make(IDS["static"])
    env.reset(seed=0)
    env.unwrapped.data.qvel[:] = np.nan  # corrupt the state behind the env's back
    obs, _, term, _, info = env.step(np.zeros(7))
    assert term and info["unstable"] and np.all(np.isfinite(obs))


def test_multiple_obstacles_collision_and_render():
    env = gym.make(
        IDS["static"],
        obstacles=[
            {"position": [0.31, 0.0, 0.49], "radius": 0.04},  # on the end-effector
            {"position": [0.3, -0.3, 0.4], "radius": 0.06, "start": [0.8, -0.3, 0.4]},
        ],
        render_mode="rgb_array",
        width=96,
        height=96,
    )
    obs, info = env.reset(seed=0)
    assert obs.shape == (29 + 12,) and env.unwrapped.n_obstacles == 2
    assert info["collision"] and info["h_per_obstacle"][0] < 0 < info["h_per_obstacle"][1]
    _, _, _, _, info = env.step(np.zeros(7))
    assert info["delta_b_true"].shape == (2,) and len(env.unwrapped.barrier_terms()) == 2
    img = env.render()
    assert img.shape == (96, 96, 3) and img.std() > 0
    env.close()


def test_raw_torque_actions_match_normalised():
    raw = FrankaObstacleEnv(normalize_action=False)
    norm = FrankaObstacleEnv()
    np.testing.assert_array_equal(raw.action_space.high, fm.TAU_MAX.astype(np.float32))
    raw.reset(seed=0)
    norm.reset(seed=0)
    u = np.array([0.5, -0.2, 0.1, 0.3, -1.0, 0.4, 0.0])
    t_raw, t_norm = raw.barrier_terms("true")[0], norm.barrier_terms("true")[0]
    np.testing.assert_allclose(t_raw.lg * fm.TAU_MAX, t_norm.lg, rtol=1e-12)
    o_raw = raw.step(u * fm.TAU_MAX)[0]
    o_norm = norm.step(u)[0]
    np.testing.assert_allclose(o_raw, o_norm, rtol=1e-6, atol=1e-6)
    policy_raw, policy_norm = NominalController(raw), NominalController(norm)
    np.testing.assert_allclose(
        policy_raw(o_raw),
        np.clip(policy_norm(o_norm) * fm.TAU_MAX, -fm.TAU_MAX, fm.TAU_MAX),
        rtol=1e-5,
        atol=1e-4,
    )


def test_perturbed_model_equals_plant_without_mismatch():
    """The separately built nominal model matches a plant with the catalogue parameters."""
    env = FrankaObstacleEnv(
        "dynamic",
        nominal_model="perturbed",
        payload_mass=0.0,
        mass_scale=1.0,
        damping=0.0,
        armature=0.0,
        warmup_steps=0,
    )
    env.reset(seed=0)
    env.set_state(fm.Q_HOME + 0.1, np.linspace(-0.4, 0.4, 7))
    env.set_time_step(300)
    tt, tn = env.barrier_terms("true")[0], env.barrier_terms("nominal")[0]
    np.testing.assert_allclose(tn.lf, tt.lf, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(tn.lg, tt.lg, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("normalize", [True, False])
def test_backup_action_is_a_saturated_joint_brake(normalize):
    env = FrankaObstacleEnv(normalize_action=normalize)
    env.reset(seed=0)
    qd = np.array([0.2, -0.8, 0.05, 1.0, -0.1, 0.3, -0.02])
    env.set_state(fm.Q_HOME, qd)
    u = env.backup_action()
    scale = 1.0 if normalize else fm.TAU_MAX
    np.testing.assert_allclose(u, np.clip(-1.0 * qd, -1, 1) * scale)
    assert env.action_space.contains(u.astype(np.float32))
    # on the real plant (payload, scaled links) braking removes most of the joint speed and
    # keeps it down (no chatter at the control period; the arm sinks slowly under its weight)
    speeds = []
    for _ in range(250):  # 1 s
        env.step(env.backup_action().astype(np.float32))
        speeds.append(np.linalg.norm(env.data.qvel))
    assert max(speeds[100:]) < 0.2 * np.linalg.norm(qd)
