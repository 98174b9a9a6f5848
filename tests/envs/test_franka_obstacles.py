"""Box, capsule and plane obstacles in the Franka env: parsing, geoms, barrier terms against
independent geometry and finite differences, contact and coverage, the oracle filter."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.agents import NominalController
from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs import primitives as pr
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.point_mass import PointMassObstacleEnv
from afvsgp_gym.envs.safety_spheres import COVERAGE_TOLERANCE
from afvsgp_gym.envs.scenario import (
    OBSTACLE_KEYS,
    OBSTACLE_TYPE_KEYS,
    ObstacleSpec,
    parse_obstacles,
    quat_to_rotation,
)
from afvsgp_gym.wrappers import SafetyFilter

C = np.array([0.3068, 0.0, 0.4872])  # the reference centre (end-effector at the ready pose)
TILT = [np.cos(0.2), 0.0, 0.0, np.sin(0.2)]  # 0.4 rad about z


def _box(pos, **kw):
    return {"type": "box", "position": list(pos), "half_sizes": [0.06, 0.04, 0.03], **kw}


def _capsule(pos, **kw):
    axis = {} if "quat" in kw else {"axis": [1.0, 0.0, 0.0]}
    return {"type": "capsule", "position": list(pos), "radius": 0.02, "half_length": 0.12,
            **axis, **kw}


TABLE = {"type": "plane", "position": [0.0, 0.0, 0.1], "normal": [0.0, 0.0, 1.0]}


# --- parsing ------------------------------------------------------------------------------

def test_parse_every_type_and_keep_spheres():
    specs = parse_obstacles([
        {"position": [0.3, 0.0, 0.5], "radius": 0.05},
        {"type": "sphere", "position": [0.3, 0.0, 0.5], "radius": 0.05, "start": [0.6, 0, 0.5]},
        _box(C, quat=TILT),
        _box(C, rotation=quat_to_rotation(TILT).tolist()),
        _capsule(C, quat=[np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]),  # z onto x
        _capsule(C, start=C + [0.3, 0, 0], start_time=1.0, speed=0.1),
        {"type": "plane", "position": [0, 0, 0.1], "normal": [0, 0, 2.0]},
    ], 3, 2.0, ("sphere", "box", "capsule", "plane"))
    assert [s.kind for s in specs] == ["sphere", "sphere", "box", "box", "capsule", "capsule",
                                       "plane"]
    assert specs[0].shape is None and specs[0].radius == 0.05 and specs[0].start is None
    assert specs[1].start_time == 2.0  # the default start time, as before
    np.testing.assert_allclose(specs[2].shape.rotation, specs[3].shape.rotation, atol=1e-15)
    np.testing.assert_allclose(specs[4].shape.axis, specs[5].shape.axis, atol=1e-15)
    assert specs[5].start_time == 1.0 and specs[5].speed == 0.1 and specs[5].duration > 0
    np.testing.assert_array_equal(specs[6].shape.normal, [0, 0, 1])
    assert specs[2].radius == pytest.approx(np.linalg.norm([0.06, 0.04, 0.03]))
    assert specs[4].radius == pytest.approx(0.14) and specs[6].radius == np.inf
    assert set(OBSTACLE_KEYS) == set().union(*OBSTACLE_TYPE_KEYS.values())
    # a spec built from a primitive is the parsed one; a Sphere gives today's sphere spec
    box = ObstacleSpec.of_shape(pr.Box(C, np.eye(3), [0.06, 0.04, 0.03]))
    assert box.kind == "box" and box.radius == pytest.approx(specs[2].radius)
    assert ObstacleSpec.of_shape(pr.Sphere(C, 0.05)).shape is None
    with pytest.raises(ValueError, match="bounding radius"):
        ObstacleSpec(C, 0.1, shape=box.shape)
    with pytest.raises(ValueError, match="static"):
        ObstacleSpec.of_shape(pr.Plane(C, [0, 0, 1]), start=C + 0.1)


@pytest.mark.parametrize(("entry", "key"), [
    ({"type": "cone", "position": [0, 0, 0]}, "type"),
    ({"type": "box", "position": [0, 0, 0]}, "half_sizes"),
    (_box(C, half_sizes=[0.1, -0.1, 0.1]), "half_sizes"),
    (_box(C, half_sizes=[0.1, 0.1]), "half_sizes"),
    (_box([0, np.nan, 0]), "position"),
    (_box(C, rotation=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "rotation"),
    (_box(C, rotation=[[0, 1, 0], [1, 0, 0], [0, 0, 1]]), "rotation"),  # a reflection
    (_box(C, quat=[0, 0, 0, 0]), "quat"),
    (_box(C, quat=TILT, rotation=np.eye(3).tolist()), "rotation"),
    (_box(C, start=[0, 0]), "start"),
    (_box(C, speed=0.0), "speed"),
    (_box(C, radius=0.1), "radius"),
    (_capsule(C, axis=[0, 0, 0]), "axis"),
    (_capsule(C, half_length=0.0), "half_length"),
    (_capsule(C, radius="x"), "radius"),
    (_capsule(C, quat=TILT, axis=[0, 0, 1]), "axis"),  # both
    (_capsule(C, half_sizes=[1, 1, 1]), "half_sizes"),
    ({**TABLE, "start": [0, 0, 0.3]}, "start"),
    ({**TABLE, "speed": 0.1}, "speed"),
    ({**TABLE, "normal": [0, 0, 0]}, "normal"),
    ({"type": "plane", "position": [0, 0, 0]}, "normal"),
    ({"position": [0, 0, 0], "radius": 0.1, "normal": [0, 0, 1]}, "normal"),
    ({"position": [0, 0, 0], "radius": -0.1}, "radius"),
])
def test_bad_obstacles_name_the_key(entry, key):
    with pytest.raises(ValueError, match=rf"obstacles\[0\]\['{key}'\]"):
        FrankaObstacleEnv(obstacles=[entry])


def test_other_envs_and_the_camera_refuse_other_types():
    with pytest.raises(ValueError, match=r"obstacles\[0\]\['type'\]"):
        PointMassObstacleEnv(obstacles=[{"type": "box", "position": [0.3, 0.0],
                                         "half_sizes": [0.1, 0.1]}])
    obstacles = [{"position": [0.3, 0.3, 0.5], "radius": 0.05}, _box(C + [0, 0.3, 0])]
    for option, value in (("obstacle_noise", 0.01), ("obstacle_delay", 0.05),
                          ("obstacle_rate", 30.0)):
        with pytest.raises(ValueError, match=rf"{option}.*obstacles\[1\] is a 'box'"):
            FrankaObstacleEnv(obstacles=obstacles, **{option: value})
    env = FrankaObstacleEnv(obstacles=obstacles, velocity_noise=0.01)  # encoders are fine
    env.reset(seed=0)
    p = np.array([C + [0, 0.3, 0]] * 2)
    with pytest.raises(ValueError, match="covariance"):
        env.set_obstacle_estimate(p, 0 * p, 0 * p, np.tile(np.eye(3), (2, 1, 1)))
    env.set_obstacle_estimate(p, 0 * p, 0 * p)  # a point estimate moves the shapes


# --- geoms and terms ----------------------------------------------------------------------

def _closest_point(spec, centre, p):
    """Independent closest surface point and signed distance of ``p`` (outside)."""
    shape = spec.primitive
    if isinstance(shape, pr.Box):
        q = shape.rotation.T @ (p - centre)
        inner = np.clip(q, -shape.half_sizes, shape.half_sizes)
        if np.any(q != inner):
            return centre + shape.rotation @ inner, np.linalg.norm(q - inner)
        return None, np.max(np.abs(q) - shape.half_sizes)
    if isinstance(shape, pr.Capsule):
        s = np.clip((p - centre) @ shape.axis, -shape.half_length, shape.half_length)
        axis_point = centre + s * shape.axis
        delta = p - axis_point
        dist = np.linalg.norm(delta)
        return axis_point + shape.radius * delta / dist, dist - shape.radius
    if isinstance(shape, pr.Plane):
        dist = (p - centre) @ shape.normal
        return p - dist * shape.normal, dist
    dist = np.linalg.norm(p - centre)
    return centre + shape.radius * (p - centre) / dist, dist - shape.radius


def _centres(env):
    m, d = env.model, env.data
    return np.array([d.xpos[m.body(s.body).id] + d.xmat[m.body(s.body).id].reshape(3, 3)
                     @ np.array(s.offset) for s in env.safety_spheres])


def test_mujoco_geoms_match_the_shapes():
    obstacles = [_box(C + [0, 0.3, 0], quat=TILT), _capsule(C + [0, -0.3, 0], axis=[1, 1, 0]),
                 {"type": "plane", "position": [0, 0, -0.01], "normal": [0, 1, 1]},
                 {"position": [0.5, 0.5, 0.5], "radius": 0.04}]
    env = FrankaObstacleEnv(obstacles=obstacles, render_mode="rgb_array", width=64, height=64)
    env.reset(seed=0)
    m, d = env.model, env.data
    geoms = [m.geom(f"obstacle{i}") for i in range(4)]
    box, cap, plane = (env.obstacles[i].shape for i in range(3))
    assert [g.type[0] for g in geoms] == [mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CAPSULE,
                                          mujoco.mjtGeom.mjGEOM_PLANE,
                                          mujoco.mjtGeom.mjGEOM_SPHERE]
    np.testing.assert_allclose(geoms[0].size, box.half_sizes)
    np.testing.assert_allclose(d.geom_xmat[geoms[0].id].reshape(3, 3), box.rotation, atol=1e-12)
    np.testing.assert_allclose(geoms[1].size[:2], [0.02, 0.12])
    np.testing.assert_allclose(d.geom_xmat[geoms[1].id].reshape(3, 3)[:, 2], cap.axis,
                               atol=1e-12)
    np.testing.assert_allclose(d.geom_xmat[geoms[2].id].reshape(3, 3)[:, 2], plane.normal,
                               atol=1e-12)
    np.testing.assert_allclose(d.geom_xpos[geoms[0].id], C + [0, 0.3, 0])
    assert geoms[3].size[0] == 0.04
    assert all(m.geom(int(g)).name.startswith("obstacle") for g in env._obstacle_geoms)
    assert env.render().std() > 0
    env.close()


SCENES = {
    "static": ([_box(C + [0.0, 0.2, -0.12], quat=TILT), _capsule(C + [0.05, -0.15, -0.1],
                axis=[1, 1, 1]), {**TABLE, "normal": [0.1, 0.0, 1.0]}], "arm"),
    "moving": ([_box(C + [0.0, 0.2, -0.12], quat=TILT, start=C + [0.3, 0.2, -0.12],
                     start_time=0.0),
                _capsule(C + [0.05, -0.15, -0.1], axis=[1, 1, 1], start=C + [0.05, -0.45, 0.1],
                         start_time=0.0, speed=0.3), TABLE], "arm"),
    "one box": ([_box(C + [0.0, 0.0, -0.17], quat=TILT, start=C + [0.3, 0.0, -0.17],
                      start_time=0.0)], "ee"),
}


@pytest.fixture(scope="module", params=list(SCENES))
def shape_env(request):
    obstacles, spheres = SCENES[request.param]
    env = FrankaObstacleEnv(obstacles=obstacles, physics_dt=1e-4, frame_skip=1,
                            warmup_steps=0, safety_spheres=spheres)
    env.reset(seed=0)
    return request.param, env


def _probe(env, q, qd, k, u):
    env.set_state(q, qd)
    env.set_time_step(k)
    env.step(u)
    return env.barrier_terms("true").derivatives.copy()


def test_shape_terms_match_finite_differences(shape_env):
    """h' from the difference of h and lf, lg from the difference of h' over a simulated
    step (u = 0 and unit actions), for boxes, capsules and planes, static and moving (the
    obstacles accelerating), as tests/envs/test_franka.py does for spheres."""
    name, env = shape_env
    rng = np.random.default_rng(1)
    q = fm.Q_HOME + rng.uniform(-0.2, 0.2, 7)
    qd = rng.uniform(-0.5, 0.5, 7)
    k = 100  # 0.01 s: every moving obstacle accelerates
    env.set_state(q, qd)
    env.set_time_step(k)
    if name != "static":
        assert np.linalg.norm(env._obstacle_states[0][2]) > 1e-3
    t0 = env.barrier_terms("true")
    n_obs = env.n_obstacle_barriers
    d_now, lf, lg = t0.derivatives[:n_obs].copy(), t0.lf[:n_obs].copy(), t0.lg[:n_obs].copy()
    dt = env.dt
    d0 = _probe(env, q, qd, k, np.zeros(7))[:n_obs]
    np.testing.assert_allclose((d0[:, 0] - d_now[:, 0]) / dt, d0[:, 1], rtol=1e-3,
                               atol=1e-4 * np.abs(d_now[:, 1]).max())
    lf_fd = (d0[:, 1] - d_now[:, 1]) / dt
    lg_fd = np.stack([(_probe(env, q, qd, k, np.eye(7)[i])[:n_obs, 1] - d0[:, 1]) / dt
                      for i in range(7)], axis=1)
    np.testing.assert_allclose(lf_fd, lf, rtol=2e-2, atol=2e-2 * np.abs(lf).max())
    np.testing.assert_allclose(lg_fd, lg, rtol=2e-2, atol=2e-2 * np.abs(lg).max())
    assert np.abs(lg).max() > 1.0
    env.set_state(q, qd)  # the nominal model goes through the same geometry
    env.set_time_step(k)
    np.testing.assert_array_equal(env.barrier_terms("nominal").derivatives,
                                  env.barrier_terms("true").derivatives)


def test_h_and_features_are_the_primitives_distances():
    """``info["h"]`` is the least pair h, each pair's h the obstacle's signed distance (an
    independent closest point) less the sphere radius, along a simulated motion; the
    features hold the sphere centre's offset from the closest point (a sphere obstacle's:
    from its centre)."""
    obstacles = [*SCENES["moving"][0], {"position": C + [0.0, -0.2, 0.15], "radius": 0.05}]
    env = FrankaObstacleEnv(obstacles=obstacles, warmup_steps=0)
    _, info = env.reset(seed=0)
    rng = np.random.default_rng(0)
    radii = np.array([s.radius for s in env.safety_spheres])
    n_s = len(radii)
    for step in range(30):
        p = _centres(env)
        h = np.empty((len(obstacles), n_s))
        offsets = np.empty((len(obstacles), n_s, 3))
        for o, (spec, (centre, _, _)) in enumerate(zip(env.obstacles, env._obstacle_states,
                                                       strict=True)):
            for s in range(n_s):
                point, dist = _closest_point(spec, centre, p[s])
                h[o, s] = dist - radii[s]
                offsets[o, s] = p[s] - (centre if spec.shape is None else point)
        np.testing.assert_allclose(info["h_per_barrier"][: h.size], h.ravel(), atol=1e-12)
        assert info["h"] == pytest.approx(h.min(), abs=1e-12)
        np.testing.assert_allclose(env.barrier_terms("true").xi[: h.size, 14:17],
                                   offsets.reshape(-1, 3), atol=1e-12)
        _, _, _, _, info = env.step(rng.uniform(-0.3, 0.3, 7) if step % 10 else np.zeros(7))


def test_reference_h_and_contact_with_every_type():
    """``reference_h`` uses each shape's distance, and an arm geom touching a box, a capsule
    or a plane (all above the hand) is a contact (cost) while the tiny sphere's h is positive."""
    tiny = [{"body": "panda0_link7", "offset": (0, 0, 0.21), "radius": 0.005}]
    hand = C + [0.0, 0.0, 0.08]  # in the hand, above the end-effector
    for obstacle in (_box(hand, half_sizes=[0.02, 0.02, 0.02]),
                     _capsule(hand, half_length=0.02),
                     {"type": "plane", "position": list(hand), "normal": [0, 0, -1]}):
        env = FrankaObstacleEnv(obstacles=[obstacle], safety_spheres=tiny)
        _, info = env.reset(seed=0)
        assert info["h"] > 0 and info["collision"] and info["cost"] == 1.0, obstacle["type"]
        spec = env.obstacles[0]
        expected = _closest_point(spec, spec.position, env._ref_state[0])[1] - env.ee_radius
        assert info["reference_h"] == pytest.approx(expected, abs=1e-12)
    env = FrankaObstacleEnv(obstacles=[{"type": "plane", "position": [0, 0, 0],
                                        "normal": [0, 0, 1]}])  # the table it stands on
    _, info = env.reset(seed=0)
    assert not info["collision"] and 0.1 < info["h"] < 0.12  # link1's spheres, 0.11 m up


@pytest.mark.skipif(not hasattr(mujoco, "mj_geomDistance"), reason="needs mj_geomDistance")
def test_collision_geoms_keep_at_least_the_spheres_clearance():
    """For random joint states, the distance of the arm's collision geoms from each obstacle
    (MuJoCo's, of the convex hulls) is at least the least pair h less COVERAGE_TOLERANCE."""
    obstacles = [_box(C + [0.1, 0.25, -0.1], quat=TILT), _capsule(C + [0.0, -0.25, 0.0],
                                                                 axis=[0, 1, 1]),
                 {"type": "plane", "position": [0.0, 0.0, 0.12], "normal": [0, 0.2, 1]},
                 {"type": "plane", "position": [0.55, 0.0, 0.0], "normal": [-1, 0, 0]},
                 {"position": C + [0.1, 0.0, 0.2], "radius": 0.06}]
    env = FrankaObstacleEnv(obstacles=obstacles)
    env.reset(seed=0)
    m, d = env.model, env.data
    rng = np.random.default_rng(0)
    lo, hi = m.jnt_range[:7, 0], m.jnt_range[:7, 1]
    n_s, margins = len(env.safety_spheres), []
    for _ in range(40):
        env.set_state(fm.Q_HOME + 0.6 * rng.uniform(-1, 1, 7) * (hi - lo) / 2, np.zeros(7))
        h = env.barrier_values()[: env.n_obstacle_barriers].reshape(-1, n_s).min(axis=1)
        for o, g_obs in enumerate(env._obstacle_geoms):
            dist = min(mujoco.mj_geomDistance(m, d, int(g), int(g_obs), 1.0, None)
                       for g in env._arm_geoms)
            if h[o] < 1.0 - COVERAGE_TOLERANCE:
                assert dist >= h[o] - COVERAGE_TOLERANCE, (o, dist, h[o])
                margins.append(dist - h[o])
    assert len(margins) > 100 and min(margins) < 0.1 * COVERAGE_TOLERANCE  # some are tight


# --- the filter ---------------------------------------------------------------------------

def _episode(filtered, steps=800):
    """Warm-up none, the y motion's full amplitude at 1 s, turning to z at 1.5 s: the hand
    meets the box (+y), the bar (going down) and comes near the table (z = 0.1 m)."""
    obstacles = [_box(C + [0.0, 0.22, -0.09], quat=TILT), _capsule(C + [0.0, 0.11, -0.17]),
                 TABLE]
    env = gym.make("afvsgp_gym/FrankaObstacleStatic-v0", obstacles=obstacles, warmup_steps=0,
                   switch_time=1.5)
    if filtered:
        env = SafetyFilter(env, learner="oracle")
    policy = NominalController(env)
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    hs, cost, collisions = [], 0.0, 0
    for _ in range(steps):
        obs, _, term, _, info = env.step(policy(obs))
        assert not term
        hs.append(info["h_per_barrier"][: base.n_obstacle_barriers].reshape(3, -1))
        cost += info["cost"]
        collisions += info["collision"]
    return np.array(hs), cost, collisions


def test_oracle_filter_avoids_box_capsule_and_table():
    hs, cost, collisions = _episode(filtered=False)
    assert hs[:, 0].min() < -0.02 and hs[:, 1].min() < -0.01  # the tracker hits both
    assert cost > 100 and collisions > 0
    hs, cost, collisions = _episode(filtered=True)
    assert cost == 0.0 and collisions == 0 and hs.min() >= 0.0
    # the moving links come near the table: its pairs are in the cone program
    assert hs[:, 2, 2:].min() < FrankaObstacleEnv.OBSTACLE_ACTIVATION
