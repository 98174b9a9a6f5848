"""Box, capsule and plane obstacles in the bridge's barrier model: the terms equal the
simulation's for the same state and obstacles, a sphere scene's are bit for bit the sphere
formulas', the covariance's gradient is the finite difference of [h, h', lf], bad input is
refused by name."""

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs import primitives as pr
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.perception import shape_pair_gradient
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, sphere_arrays
from afvsgp_gym.envs.scenario import ObstacleSpec, quat_to_rotation
from afvsgp_gym.robots.kinematics import GYMNASIUM_PANDA, SphereKinematics
from afvsgp_gym.robots.run import obstacle_specs, scripted_obstacles
from afvsgp_gym.robots.terms import BarrierModel, ObstacleEstimate, panda_self_collision_pairs

EPS = np.finfo(np.float64).eps
C = np.array([0.3068, 0.0, 0.4872])  # the reference centre (end-effector at the ready pose)
TILT = [np.cos(0.2), 0.0, 0.0, np.sin(0.2)]  # 0.4 rad about z
#: A box that moves in onto the path, a tilted capsule, a table at the mount and a sphere.
OBSTACLES = [
    {"type": "box", "position": (C + [0.0, 0.18, -0.12]).tolist(),
     "half_sizes": [0.06, 0.04, 0.03], "quat": TILT,
     "start": (C + [0.4, 0.18, -0.12]).tolist(), "start_time": 0.5, "speed": 0.2},
    {"type": "capsule", "position": (C + [0.05, -0.2, -0.05]).tolist(), "radius": 0.03,
     "half_length": 0.12, "axis": [1.0, 0.3, 0.2]},
    {"type": "plane", "position": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
    {"type": "sphere", "position": (C + [0.0, 0.0, 0.2]).tolist(), "radius": 0.05},
]
KINEMATICS = SphereKinematics.from_spheres(GYMNASIUM_PANDA, PANDA_ARM_SPHERES)
RADII = sphere_arrays(PANDA_ARM_SPHERES)[2]


@pytest.fixture(scope="module")
def env():
    # the exact model of a plant whose gravity the robot compensates fully (test_terms.py)
    e = FrankaObstacleEnv(obstacles=OBSTACLES, nominal_model="exact", payload_mass=0.0,
                          mass_scale=1.0, damping=0.0, friction=0.0, normalize_action=False)
    e.reset(seed=0)
    yield e
    e.close()


def _model_of(env):
    """``M`` and ``c = C q'`` of the plant at its state (gravity cancelled by gravcomp)."""
    m, d = env.model, env.data
    full = np.empty((m.nv, m.nv))
    for i, e in enumerate(np.eye(m.nv)):
        mujoco.mj_mulM(m, d, full[i], e)
    return full, d.qfrc_bias - d.qfrc_passive


def _estimate(env, covariance=None):
    states = env._obstacle_states
    return ObstacleEstimate(*(np.array([s[j] for s in states]) for j in range(3)), covariance)


def _bridge_model(obstacles, limits=None, action_scale=1.0, self_collision=None):
    return BarrierModel(KINEMATICS, RADII, [o.radius for o in obstacles], limits, action_scale,
                        shapes=[o.shape for o in obstacles], self_collision=self_collision)


def test_terms_equal_the_simulations_with_a_box_a_capsule_and_a_table(env):
    """Every term at 40 states (random and near the ready pose, the box anywhere on its way
    in). The geometry is the same code (pair_barriers) on the same inputs up to the
    kinematics (the DH chain equals MuJoCo's to ~1e-15 m here) and M^-1 (numpy's inverse vs
    MuJoCo's factorisation, relative error ~ cond(M) eps ~ 1e-12); n is 1/rho-Lipschitz with
    rho >= ~1 cm, so h, h', xi and lg agree to 1e-12 and lf, which holds J M^-1 c with c up
    to ~100 Nm, to 1e-9 (test_terms.py's tolerances for spheres)."""
    base = env.unwrapped
    model = _bridge_model(base.obstacles, base.joint_limits, base.action_scale,
                          panda_self_collision_pairs())  # the env's default
    assert [o.kind for o in base.obstacles] == ["box", "capsule", "plane", "sphere"]
    rng = np.random.default_rng(4)
    lim = base.joint_limits
    for i in range(40):
        q = rng.uniform(lim.lower + 0.05, lim.upper - 0.05)
        if i % 2:  # near the ready pose: the spheres close to the box's and capsule's places
            q = base.q_home + rng.uniform(-0.3, 0.3, 7)
        qd = rng.uniform(-1.5, 1.5, 7)
        base.set_time_step(int(rng.integers(0, 1500)))
        base.set_state(q, qd)
        want = base.barrier_terms("nominal")
        mass, coriolis = _model_of(base)
        got = model.terms(q, qd, mass, coriolis, _estimate(base))
        np.testing.assert_allclose(got.derivatives, want.derivatives, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.xi, want.xi, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.lg, want.lg, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got.lf, want.lf, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(got.projection, want.projection, rtol=0, atol=1e-12)
        assert got.covariance is None and want.covariance is None
        np.testing.assert_array_equal(model.sphere_clearance(q, _estimate(base).position),
                                      got.h[:model.n_pairs])


def test_a_sphere_scene_keeps_the_sphere_formulas_bit_for_bit():
    """shapes=None, all None and Sphere primitives: the same numbers, the sphere path's."""
    rng = np.random.default_rng(1)
    radii = [0.05, 0.08]
    plain = BarrierModel(KINEMATICS, RADII, radii, None)
    for shapes in ([None, None], [pr.Sphere([1.0, 2.0, 3.0], 0.05), None]):
        other = BarrierModel(KINEMATICS, RADII, radii, None, shapes=shapes)
        assert other.shapes == (None, None)
        q, qd = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7)
        a = rng.normal(size=(7, 7))
        est = ObstacleEstimate(rng.normal(size=(2, 3)) * 0.4, rng.normal(size=(2, 3)),
                               rng.normal(size=(2, 3)), np.tile(np.eye(3) * 1e-4, (2, 1, 1)))
        x = plain.terms(q, qd, a @ a.T + np.eye(7), np.ones(7), est)
        y = other.terms(q, qd, a @ a.T + np.eye(7), np.ones(7), est)
        for field in ("derivatives", "lf", "lg", "xi", "covariance"):
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field))


def _pair_state_function(shape, p_s, v_s, a_s, radius):
    """``F(c, c', c'') = [h, h', lf]`` of one (sphere, shape) pair, ``lf = n.(a_s - c'') +
    curvature`` (the terms' lf less the parts without the obstacle)."""
    def f(c, cv, ca):
        h, hd, n, curv = pr.pair_barriers([shape], (p_s - c)[None], (v_s - cv)[None], radius)
        return np.array([h[0], hd[0], n[0] @ (a_s - ca) + curv[0]])
    return f


def _region_cases():
    """(shape, p_rel, length scale): a point of each region of each primitive, at least
    2 cm from the boundaries between regions (where H jumps) and from the feature."""
    rot = quat_to_rotation([0.9, 0.2, -0.3, 0.25])
    box = pr.Box(np.zeros(3), rot, [0.1, 0.15, 0.2])
    cap = pr.Capsule(np.zeros(3), rot[:, 2], 0.15, 0.04)
    side = rot[:, 0] * 0.1 + rot[:, 2] * 0.05
    end = rot[:, 2] * 0.2 + rot[:, 1] * 0.03
    return [
        (box, rot @ [0.15, 0.02, -0.03], 0.05), (box, rot @ [0.15, 0.2, 0.05], 0.05),
        (box, rot @ [0.15, 0.2, 0.26], 0.05), (box, rot @ [0.05, 0.01, 0.02], 0.05),
        (cap, side, 0.05), (cap, end, 0.05),
        (pr.Sphere(np.zeros(3), 0.05), np.array([0.1, -0.15, 0.05]), 0.1),
        (pr.Plane(np.zeros(3), [0.3, -0.2, 1.0]), np.array([0.3, 0.4, 0.2]), 1.0),
    ]


@pytest.mark.parametrize("case", range(8), ids=["box-face", "box-edge", "box-corner",
                                                "box-inside", "capsule-side", "capsule-end",
                                                "sphere", "plane"])
def test_the_covariances_gradient_is_the_finite_difference_of_h_h1_lf(case):
    """Central differences of F(c, c', c'') in each of the nine coordinates, step
    delta = eps^(1/3) l (l the case's length scale): truncation (delta^2 / 6) |F'''| with
    |F'''| ~ |F'| / l^2 and rounding eps |F| / delta, so the error is at most
    eps^(2/3) (|F'| + |F| / l) up to a constant (10, from the model, not fitted)."""
    shape, p_rel, ell = _region_cases()[case]
    rng = np.random.default_rng(case)
    c0, cv, ca = np.array([0.2, -0.1, 0.3]), rng.normal(size=3), rng.normal(size=3)
    v_s, a_s = cv + rng.normal(size=3), ca + rng.normal(size=3)
    f = _pair_state_function(shape, c0 + p_rel, v_s, a_s, 0.03)
    stack = pr.hessian_stack([shape], 1)
    hess = pr.pair_hessians(stack, p_rel[None])
    n = pr.pair_barriers([shape], p_rel[None], (v_s - cv)[None], 0.03)[2]
    grad = shape_pair_gradient(n, hess, (v_s - cv)[None], (a_s - ca)[None])[0]
    step = EPS ** (1 / 3) * ell
    base = (c0, cv, ca)
    fd = np.empty((3, 3, 3))
    for which in range(3):
        for axis in range(3):
            e = np.zeros(3)
            e[axis] = step
            hi = [x + e if j == which else x for j, x in enumerate(base)]
            lo = [x - e if j == which else x for j, x in enumerate(base)]
            fd[:, which, axis] = (f(*hi) - f(*lo)) / (2 * step)
    tol = 10 * EPS ** (2 / 3) * (np.abs(grad).max() + np.abs(f(*base)).max() / ell)
    np.testing.assert_allclose(grad, fd, rtol=0, atol=tol)


def test_a_shaped_scenes_covariance_is_the_sphere_formulas_for_its_spheres():
    """With a plane in the scene every pair goes through shape_pair_covariance: its sphere
    rows equal pair_covariance (the same formulas through H = P / |d|, to rounding: entries
    ~ sigma^2 |grad|^2, relative error ~ 1e-13 from forming H by polarisation) and lf's
    mean error is 2 sigma_v^2 / |d| there, 0 for the plane's (H = 0)."""
    rng = np.random.default_rng(2)
    table = ObstacleSpec.of_shape(pr.Plane([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]))
    ball = ObstacleSpec(C + [0.0, 0.2, -0.07], 0.05)
    model = _bridge_model([ball, table])
    spheres = _bridge_model([ball])
    q, qd = rng.uniform(-0.5, 0.5, 7), rng.normal(size=7)
    a = rng.normal(size=(7, 7))
    mass, coriolis = a @ a.T + np.eye(7), rng.normal(size=7)
    cov = np.array([[[1e-4, 2e-5, 0.0], [2e-5, 4e-4, 0.0], [0.0, 0.0, 0.0]]] * 2)
    pos = np.array([ball.position, table.position])
    est = ObstacleEstimate(pos, rng.normal(size=(2, 3)) * 0.1, np.zeros((2, 3)), cov)
    got = model.terms(q, qd, mass, coriolis, est)
    exact = model.terms(q, qd, mass, coriolis, ObstacleEstimate(est.position, est.velocity,
                                                                est.acceleration))
    ref = spheres.terms(q, qd, mass, coriolis, ObstacleEstimate(pos[:1], est.velocity[:1],
                                                                est.acceleration[:1], cov[:1]))
    s = model.n_spheres
    scale = np.abs(ref.covariance[:s]).max()
    np.testing.assert_allclose(got.covariance[:s], ref.covariance[:s], rtol=0,
                               atol=1e-12 * scale)
    np.testing.assert_allclose(got.lf[:s], ref.lf[:s], rtol=1e-12, atol=1e-12)
    d = np.linalg.norm(got.xi[:s, 14:17], axis=1)
    np.testing.assert_allclose(exact.lf[:s] - got.lf[:s], 2 * cov[0, 1, 1] / d, rtol=1e-9)
    np.testing.assert_allclose(got.lf[s:2 * s], exact.lf[s:2 * s], rtol=0, atol=1e-15)
    # the plane: h = m.p - r, h' = m.v_rel, lf's obstacle part -m.a_o: the rows [-m; 0; 0],
    # [0; -m; 0] and [0; 0; -m] contracted with the per-axis covariance, |m| = 1
    np.testing.assert_allclose(got.covariance[s:2 * s], np.broadcast_to(cov[1], (s, 3, 3)),
                               rtol=1e-12, atol=1e-18)


def test_bad_shapes_are_refused_by_name():
    box = ObstacleSpec.of_shape(pr.Box(C, np.eye(3), [0.05, 0.05, 0.05]))
    with pytest.raises(ValueError, match=r"shapes\[0\] must be a Box"):
        BarrierModel(KINEMATICS, RADII, [box.radius], None, shapes=["box"])
    with pytest.raises(ValueError, match=r"shapes must be None or a sequence of 2"):
        BarrierModel(KINEMATICS, RADII, [box.radius, 0.05], None, shapes=[box.shape])
    with pytest.raises(ValueError, match=r"obstacle_radii\[0\] must be shapes\[0\]'s bounding"):
        BarrierModel(KINEMATICS, RADII, [0.05], None, shapes=[box.shape])
    with pytest.raises(ValueError, match=r"obstacle_radii\[0\] of a sphere must be finite"):
        BarrierModel(KINEMATICS, RADII, [np.inf], None)
    with pytest.raises(ValueError, match="obstacle_radii"):
        BarrierModel(KINEMATICS, RADII, [np.nan], None)
    with pytest.raises(ValueError, match="half_sizes must be > 0"):
        pr.Box(C, np.eye(3), [0.05, 0.0, 0.05])
    with pytest.raises(ValueError, match="center"):
        pr.Capsule([0.0, np.nan, 0.0], [0, 0, 1], 0.1, 0.02)
    with pytest.raises(ValueError, match="normal must be a non-zero vector"):
        pr.Plane(C, [0.0, 0.0, 0.0])
    model = _bridge_model([box])
    with pytest.raises(ValueError, match="obstacles must be an ObstacleEstimate of 1"):
        model.terms(np.zeros(7), np.zeros(7), np.eye(7), np.zeros(7),
                    ObstacleEstimate(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3))))



def test_pair_hessians_give_the_kernels_curvature_as_a_quadratic_form():
    """v' H v is the kernels' curvature for every v (to rounding: entries ~ 1 / rho with
    rho >= 2 cm here, four roundings each), H symmetric and positive semi-definite."""
    rng = np.random.default_rng(6)
    shapes = [case[0] for case in _region_cases()]
    points = np.array([case[1] for case in _region_cases()])
    hess = pr.pair_hessians(pr.hessian_stack(shapes, 1), points)
    np.testing.assert_array_equal(hess, hess.transpose(0, 2, 1))
    assert np.linalg.eigvalsh(hess).min() > -1e-12
    for _ in range(5):
        v = rng.normal(size=points.shape)
        curv = pr.pair_barriers(pr.stack_shapes(shapes, 1), points, v, 0.01)[3]
        np.testing.assert_allclose(np.einsum("ki,kij,kj->k", v, hess, v), curv, rtol=1e-12,
                                   atol=1e-12)
    with pytest.raises(ValueError, match="hessian_stack"):
        pr.pair_hessians(pr.stack_shapes(shapes, 1), points)


def test_virtual_obstacles_for_a_robot_take_the_envs_dicts_and_fixed_spheres():
    specs = obstacle_specs([OBSTACLES[2], OBSTACLES[0], (0.5, 0.0, 0.3, 0.05)])
    assert [o.kind for o in specs] == ["plane", "box", "sphere"]
    assert specs[1].start_time == 0.5 and specs[2].radius == 0.05
    callback = scripted_obstacles(specs)
    est = callback(10.0)  # the box has arrived
    np.testing.assert_array_equal(est.position, [o.position for o in specs])
    moving = callback(0.5 + specs[1].duration / 2)
    assert np.linalg.norm(moving.velocity[1]) > 0 and not moving.velocity[[0, 2]].any()
    fixed = scripted_obstacles([specs[0], specs[2]])
    assert fixed(0.0) is fixed(5.0)  # static: one estimate for every tick
    assert scripted_obstacles([])(0.0).position.shape == (0, 3)
    assert obstacle_specs([]) == []
    with pytest.raises(ValueError, match=r"obstacles\[0\]\['type'\] must be one of"):
        obstacle_specs([{"type": "cone", "position": [0, 0, 0]}])
    with pytest.raises(ValueError, match=r"obstacles\[1\] must be an ObstacleSpec"):
        obstacle_specs([OBSTACLES[2], (0.5, 0.0, 0.3)])
    with pytest.raises(ValueError, match=r"obstacles\[0\]\['radius'\] must be > 0"):
        obstacle_specs([(0.5, 0.0, 0.3, -0.05)])
