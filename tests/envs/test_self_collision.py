"""Self-collision of the Franka arm: the pair table re-derived, the barrier terms against
finite differences of the simulation and an independent computation, the barriers' place
among the others, the self-contact flag against a direct check, the oracle filter."""

import json
import pathlib
import subprocess
import sys

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs import self_collision as sc
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.safety_spheres import (
    COVERAGE_TOLERANCE,
    PANDA_ARM_SPHERES,
    PANDA_BASE_SPHERES,
)
from afvsgp_gym.evaluation.factories import make_policy
from afvsgp_gym.wrappers import EpisodeSafetyStats, SafetyFilter

#: Folds the arm so that the fingers sink ~2 cm into link1, the column on the base.
FOLDED = np.array([0.0, 0.0, 0.0, -2.8, 0.0, -0.3, 0.785])
#: A deeper fold (fingers ~6 cm into link1), inside the joint-limit barriers' margins.
FOLD_TARGET = np.array([0.0, 0.2, 0.0, -2.9, 0.0, -0.3, 0.785])
SPHERES = sc.PANDA_SELF_COLLISION_SPHERES
N_ARM = len(PANDA_ARM_SPHERES)
#: Every candidate pair's clearances, written by benchmarks/select_self_pairs.py.
MINIMA = pathlib.Path(__file__).parents[2] / "benchmarks" / "results" / "self_pairs.json"


def _self_rows(env) -> slice:
    k = env.n_obstacle_barriers
    return slice(k, k + env.n_self_collision_barriers)


# --- the pair table ----------------------------------------------------------------------

def _chain_depth(m: mujoco.MjModel, body: int) -> int:
    """Depth of ``body`` in MuJoCo's body tree (world 0, link0 1, link1 2, ...)."""
    depth = 0
    while body:
        body, depth = int(m.body_parentid[body]), depth + 1
    return depth


def _sphere_links(m: mujoco.MjModel) -> np.ndarray:
    """The link of each sphere (the arm's and the base's) from the body tree; link7's
    spheres past the flange (the hand's) one further, with the fingers (children of link7)."""
    return np.array([_chain_depth(m, m.body(s.body).id)
                     + (s.body == "panda0_link7" and s.offset[2] > fm.FLANGE_POS[2])
                     for s in SPHERES])


def _centres(m, d, q):
    d.qpos[:7] = q
    mujoco.mj_kinematics(m, d)
    return np.array([d.xpos[m.body(s.body).id] + d.xmat[m.body(s.body).id].reshape(3, 3)
                     @ np.array(s.offset) for s in SPHERES])


def _pair_h(p, pairs):
    radii = np.array([s.radius for s in SPHERES])
    a, b = pairs[:, 0], pairs[:, 1]
    return np.linalg.norm(p[a] - p[b], axis=1) - radii[a] - radii[b]


@pytest.fixture(scope="module")
def derivation():
    """The selection's inputs: the candidates from the body tree, their clearance at the
    ready pose (computed here), and their sampled and refined minima and the refined
    minimiser (``witness``) from benchmarks/results/self_pairs.json."""
    m = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    d = mujoco.MjData(m)
    link = _sphere_links(m)
    a, b = np.triu_indices(len(link), 1)
    candidates = np.column_stack([a, b])[np.abs(link[a] - link[b]) >= 2]
    home = _pair_h(_centres(m, d, fm.Q_HOME), candidates)
    table = json.loads(MINIMA.read_text())
    rows = table.pop("pairs")
    assert table == {"clearance": sc.SELF_COLLISION_CLEARANCE, "samples": sc.SELECTION_SAMPLES,
                     "seed": sc.SELECTION_SEED, "refine_starts": sc.REFINE_STARTS}
    np.testing.assert_array_equal([r["pair"] for r in rows], candidates)
    np.testing.assert_allclose([r["home"] for r in rows], home, rtol=0, atol=1e-12)
    sampled = np.array([r["sampled"] for r in rows])
    refined = np.array([r["refined"] for r in rows])
    witness = np.array([r["q"] for r in rows])
    return candidates, home, refined, witness, sampled


def _kept(derivation) -> np.ndarray:
    candidates, home, refined = derivation[:3]
    return (home >= 0) & (refined < sc.SELF_COLLISION_CLEARANCE)


def test_pair_table_is_rederived(derivation):
    """Non-adjacent links only (the base link 0, the hand and fingers one link after link7),
    none overlapping at the ready pose, each able to come within the clearance by the
    committed minima: the committed table, with the counts the module docstring gives."""
    candidates, home, refined, _, _ = derivation
    assert sc.FLANGE_HEIGHT == fm.FLANGE_POS[2]
    assert SPHERES == PANDA_ARM_SPHERES + PANDA_BASE_SPHERES
    np.testing.assert_array_equal(sc.non_adjacent_pairs(SPHERES), candidates)
    kept = _kept(derivation)
    assert {tuple(p) for p in candidates[kept]} == set(sc.PANDA_SELF_COLLISION_PAIRS)
    assert len(sc.PANDA_SELF_COLLISION_PAIRS) == len(set(sc.PANDA_SELF_COLLISION_PAIRS))
    assert (len(candidates), int((home < 0).sum()), int((~kept & (home >= 0)).sum()),
            int(kept.sum())) == (184, 1, 90, 93)
    base = candidates[:, 1] >= N_ARM
    assert (int(base.sum()), int((kept & base).sum())) == (38, 26)
    assert [tuple(p) for p in candidates[home < 0]] == [(9, 15)]  # link5[9]/link7[15]
    # no two spheres of one link or of neighbouring links are paired
    links = _sphere_links(fm.build_model(fm.PlantParameters(), fm.SceneOptions()))
    assert all(abs(links[a] - links[b]) >= 2 for a, b in sc.PANDA_SELF_COLLISION_PAIRS)
    # the base with link2 (two apart): candidates, none kept
    link2 = base & (links[candidates[:, 0]] == links[N_ARM] + 2)
    assert link2.sum() == 4 and not kept[link2].any()
    assert refined[link2].min() > 0.08


def test_the_committed_minima_are_attained_and_below_the_samples(derivation):
    """Each refined minimum is the clearance at its minimiser, within the joint ranges, and
    at most the sampled one, which is at most the least over the first 2000 of the table's
    draws (computed here)."""
    candidates, _, refined, witness, sampled = derivation
    m = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    d = mujoco.MjData(m)
    lo, hi = m.jnt_range[:7, 0], m.jnt_range[:7, 1]
    assert np.all((witness >= lo) & (witness <= hi))
    at = np.array([_pair_h(_centres(m, d, q), candidates[c : c + 1])[0]
                   for c, q in enumerate(witness)])
    np.testing.assert_allclose(at, refined, rtol=0, atol=1e-12)
    assert np.all(refined <= sampled)
    rng = np.random.default_rng(sc.SELECTION_SEED)
    q = rng.uniform(lo, hi, (sc.SELECTION_SAMPLES, 7))[:2000]
    least = np.min([_pair_h(_centres(m, d, qi), candidates) for qi in q], axis=0)
    assert np.all(sampled <= least + 1e-12)  # (the same numbers summed in another order)
    assert (sampled - refined).max() > 0.02  # the refinement finds what the samples miss


def test_left_out_pairs_stay_apart_from_other_starts(derivation):
    """Minimising again every pair left out by its clearance, from other draws (seed 1, the
    5 best of 2000 for each): none comes within the clearance."""
    from select_self_pairs import PairClearance, refine

    candidates, home, refined, _, _ = derivation
    far = np.flatnonzero((home >= 0) & (refined >= sc.SELF_COLLISION_CLEARANCE))
    clearance = PairClearance(fm.build_model(fm.PlantParameters(), fm.SceneOptions()))
    m = clearance.model
    q = np.random.default_rng(1).uniform(m.jnt_range[:7, 0], m.jnt_range[:7, 1], (2000, 7))
    h = clearance.values(q, candidates[far])
    again = np.array([refine(clearance, tuple(int(i) for i in candidates[c]),
                             q[np.argsort(h[:, j])[: sc.REFINE_STARTS]])[0]
                      for j, c in enumerate(far)])
    assert np.all(again >= sc.SELF_COLLISION_CLEARANCE)
    assert np.abs(again - refined[far]).max() < 0.01  # the same minima, near enough


def test_a_kept_pair_meets_in_a_configuration(derivation):
    """The closest approach of the kept pairs overlaps (the barriers are not idle): it is
    a pair with the base, and the env's barrier reads that pair's h at its minimiser."""
    candidates, home, refined, witness, _ = derivation
    kept = np.flatnonzero(_kept(derivation))
    c = kept[np.argmin(refined[kept])]
    assert refined[c] < 0 and candidates[c, 1] >= N_ARM
    env = FrankaObstacleEnv(self_collision=True)
    env.reset(seed=0)
    env.set_state(witness[c], np.zeros(7))
    row = sc.PANDA_SELF_COLLISION_PAIRS.index(tuple(candidates[c]))
    h = env.barrier_values()[_self_rows(env)]
    assert h[row] == pytest.approx(refined[c], abs=1e-12)
    assert h.min() == pytest.approx(h[row], abs=0.05)  # it is among the closest


def test_the_module_needs_no_simulator():
    code = ("import sys; import afvsgp_gym.envs.self_collision as sc; "
            "print(len(sc.PANDA_SELF_COLLISION_PAIRS), 'mujoco' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == [str(len(sc.PANDA_SELF_COLLISION_PAIRS)), "False"]


def test_chain_index_and_pairs_refuse_what_they_do_not_know():
    assert sc.chain_index("panda0_link7", 0.05) == 7
    assert sc.chain_index("panda0_link7", 0.2) == sc.HAND_INDEX
    assert sc.chain_index("panda0_rightfinger") == sc.HAND_INDEX
    assert sc.chain_index("panda0_link0", 0.3) == sc.BASE_INDEX == 0
    for body in ("panda0_link8", "world", "obstacle0"):
        with pytest.raises(ValueError, match="is not a link of the Panda"):
            sc.chain_index(body)
    with pytest.raises(ValueError, match="pairs must index"):
        sc.SelfCollisionPairs.of(PANDA_ARM_SPHERES, [(0, 21)])
    with pytest.raises(ValueError, match="different spheres"):
        sc.SelfCollisionPairs.of(PANDA_ARM_SPHERES, [(3, 3)])
    with pytest.raises(ValueError, match="pairs must join a moving sphere"):
        sc.SelfCollisionPairs.of(SPHERES, [(0, 21), (21, 22)], fixed_centres=np.zeros((2, 3)))
    for bad in (np.zeros((24, 3)), [[0.0, np.nan, 0.0]]):
        with pytest.raises(ValueError, match="fixed_centres must be finite"):
            sc.SelfCollisionPairs.of(SPHERES, [(0, 5)], fixed_centres=bad)
    pairs = sc.SelfCollisionPairs.of(PANDA_ARM_SPHERES, [(0, 5)])  # nothing fixed
    assert pairs.n_moving == N_ARM and pairs.fixed.shape == (0, 3)


# --- the base's spheres ------------------------------------------------------------------

def _base_spheres(m, d):
    """World centres (2, 3) and radii of PANDA_BASE_SPHERES."""
    b = m.body("panda0_link0").id
    centres = np.array([d.xpos[b] + d.xmat[b].reshape(3, 3) @ np.array(s.offset)
                        for s in PANDA_BASE_SPHERES])
    return centres, np.array([s.radius for s in PANDA_BASE_SPHERES])


def test_base_spheres_cover_every_vertex_of_its_collision_mesh():
    """As the arm's (test_franka): every vertex of link0's collision mesh lies inside the
    union of PANDA_BASE_SPHERES up to COVERAGE_TOLERANCE."""
    m = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    centres, radii = _base_spheres(m, d)
    points = []
    for g in _base_geoms(m):
        assert m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
        i = m.geom_dataid[g]
        local = m.mesh_vert[m.mesh_vertadr[i] : m.mesh_vertadr[i] + m.mesh_vertnum[i]]
        points.append(d.geom_xpos[g] + local @ d.geom_xmat[g].reshape(3, 3).T)
    points = np.vstack(points)
    gap = np.min(np.linalg.norm(points[:, None] - centres[None], axis=2) - radii, axis=1)
    assert len(points) > 50 and gap.max() <= COVERAGE_TOLERANCE


@pytest.mark.skipif(not hasattr(mujoco, "mj_geomDistance"), reason="needs mj_geomDistance")
def test_base_geom_keeps_at_least_its_spheres_clearance():
    """As the arm's (test_franka_obstacles): for sphere probes of 1, 5 and 15 cm round the
    base, MuJoCo's distance from link0's collision geom is at least the base spheres' least
    clearance less COVERAGE_TOLERANCE, and tight for some."""
    radii_probe = (0.01, 0.05, 0.15)
    env = FrankaObstacleEnv(obstacles=[{"position": [2.0, 2.0 * i, 1.0], "radius": r}
                                       for i, r in enumerate(radii_probe)])
    env.reset(seed=0)
    m, d = env.model, env.data
    centres, radii = _base_spheres(m, d)
    (g_base,) = _base_geoms(m)
    rng = np.random.default_rng(0)
    margins = []
    for _ in range(150):
        for i, r in enumerate(radii_probe):
            c = rng.uniform([-0.35, -0.3, -0.15], [0.3, 0.3, 0.4])
            d.mocap_pos[env._obstacle_mocap[i]] = c
            mujoco.mj_kinematics(m, d)
            h = np.min(np.linalg.norm(c - centres, axis=1) - radii) - r
            if h < 0.2:
                dist = mujoco.mj_geomDistance(m, d, int(g_base), int(env._obstacle_geoms[i]),
                                              1.0, None)
                assert dist >= h - COVERAGE_TOLERANCE, (c, r, dist, h)
                margins.append(dist - h)
    assert len(margins) > 100 and min(margins) < 0.1 * COVERAGE_TOLERANCE  # some are tight


# --- the terms ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fd_env():
    """Steps of 0.1 ms, one per action: finite differences resolve h'' to ~1e-3."""
    env = FrankaObstacleEnv(self_collision=True, physics_dt=1e-4, frame_skip=1, warmup_steps=0,
                            nominal_model="perturbed")
    env.reset(seed=0)
    return env


def _near_contact_state(derivation, base: bool, clearance=0.005):
    """A state approaching contact: on the segment from the ready pose to the minimiser of
    the deepest kept pair with the base (``base``) or of two moving spheres, where its h is
    within ``clearance``, moving on along the segment (h' < 0)."""
    candidates, _, closest, witness, _ = derivation
    kept = np.flatnonzero(_kept(derivation) & ((candidates[:, 1] >= N_ARM) == base))
    c = kept[np.argmin(closest[kept])]
    m = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    d = mujoco.MjData(m)
    lo, hi = 0.0, 1.0  # bisect h(Q_HOME + s (witness - Q_HOME)) = clearance / 2
    for _ in range(40):
        s = 0.5 * (lo + hi)
        q = fm.Q_HOME + s * (witness[c] - fm.Q_HOME)
        h = _pair_h(_centres(m, d, q), candidates[c : c + 1])
        lo, hi = (s, hi) if h[0] > 0.5 * clearance else (lo, s)
    q = fm.Q_HOME + lo * (witness[c] - fm.Q_HOME)
    qd = 0.5 * (witness[c] - fm.Q_HOME) / np.linalg.norm(witness[c] - fm.Q_HOME)
    return q, qd, sc.PANDA_SELF_COLLISION_PAIRS.index(tuple(candidates[c]))


def _probe(env, q, qd, u):
    env.set_state(q, qd)
    env.step(u)
    return env.barrier_terms("true").derivatives[_self_rows(env)].copy()


@pytest.mark.parametrize("state", ["random", "near contact", "near the base"])
def test_terms_match_finite_differences(fd_env, derivation, state):
    """h' from the difference of h, lf and lg from the difference of h' over one simulated
    step at u = 0 and unit actions. The error model of test_franka_obstacles: a forward
    difference over dt = 1e-4 s misses dt/2 h''' and the Euler step's implicit damping
    shifts q'' by ~dt D M^-1 (1e-3 of it), both under the 2 % (relative, and of the largest
    term) allowed; h' from h is first order in dt too (1e-3). Near the base the pair's
    second sphere is fixed (zero velocity and Jacobian): its terms are the moving one's."""
    env, rows = fd_env, _self_rows(fd_env)
    if state == "random":
        rng = np.random.default_rng(3)
        q, qd = fm.Q_HOME + rng.uniform(-0.3, 0.3, 7), rng.uniform(-0.5, 0.5, 7)
    else:
        q, qd, row = _near_contact_state(derivation, base=state == "near the base")
        assert (sc.PANDA_SELF_COLLISION_PAIRS[row][1] >= N_ARM) == (state == "near the base")
    env.set_state(q, qd)
    t0 = env.barrier_terms("true")
    d_now, lf, lg = t0.derivatives[rows].copy(), t0.lf[rows].copy(), t0.lg[rows].copy()
    if state == "near contact":
        assert 0.0 < d_now[row, 0] < 0.005 and d_now[row, 1] < 0.0  # approaching
    dt = env.dt
    d0 = _probe(env, q, qd, np.zeros(7))
    np.testing.assert_allclose((d0[:, 0] - d_now[:, 0]) / dt, d0[:, 1], rtol=1e-3,
                               atol=1e-4 * np.abs(d_now[:, 1]).max())
    lf_fd = (d0[:, 1] - d_now[:, 1]) / dt
    lg_fd = np.stack([(_probe(env, q, qd, np.eye(7)[i])[:, 1] - d0[:, 1]) / dt
                      for i in range(7)], axis=1)
    np.testing.assert_allclose(lf_fd, lf, rtol=2e-2, atol=2e-2 * np.abs(lf).max())
    np.testing.assert_allclose(lg_fd, lg, rtol=2e-2, atol=2e-2 * np.abs(lg).max())
    assert np.abs(lg).max() > 1.0
    if state != "random":  # that pair's own row, to its own scale
        np.testing.assert_allclose(lg_fd[row], lg[row], rtol=2e-2,
                                   atol=2e-2 * np.abs(lg[row]).max())
        assert abs(lf_fd[row] - lf[row]) <= 2e-2 * max(abs(lf[row]), np.abs(lf).max() / 10)
        assert np.abs(lg[row]).max() > 0.1


def _independent_terms(m, state, pairs):
    """lf, lg of the sphere ``pairs`` for model ``m`` at the joint state of ``state``, from
    MuJoCo's Jacobians, their time derivative and M^-1 (no env code)."""
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = state.qpos, state.qvel
    mujoco.mj_forward(m, d)
    minv = np.empty((m.nv, m.nv))
    mujoco.mj_solveM(m, d, minv, np.eye(m.nv))
    out = []
    for s in SPHERES:  # link0's: MuJoCo's Jacobians of a body without joints are 0
        body = m.body(s.body).id
        p = d.xpos[body] + d.xmat[body].reshape(3, 3) @ np.array(s.offset)
        jac, jdot = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jac, None, p, body)
        mujoco.mj_jacDot(m, d, jdot, None, p, body)
        out.append((p, jac @ d.qvel, jac @ d.qacc + jdot @ d.qvel, jac @ minv * fm.TAU_MAX))
    lf, lg = [], []
    for a, b in pairs:
        (pa, va, aa, ga), (pb, vb, ab, gb) = out[a], out[b]
        dist = np.linalg.norm(pa - pb)
        n, vr = (pa - pb) / dist, va - vb
        lf.append(n @ (aa - ab) + (vr @ vr - (n @ vr) ** 2) / dist)
        lg.append(n @ (ga - gb))
    return np.array(lf), np.array(lg)


def _with_base(pairs, p, v, jac, bias):
    """The arm spheres' kinematics with the base's after them: where they are fixed, with
    zero velocity, Jacobian and ``J' q'``."""
    f = len(pairs.fixed)
    return (np.concatenate([p, pairs.fixed]), np.concatenate([v, np.zeros((f, 3))]),
            np.concatenate([jac, np.zeros((f, *jac.shape[1:]))]),
            np.concatenate([bias, np.zeros((f, 3))]))


def test_every_model_and_the_barriers_around_them():
    """At one state: the perturbed model's self terms equal an independent computation on
    the catalogue model, the kinematic one keeps the curvature and J' q' with lg = 0, the
    zero one nothing; the obstacle and joint-limit rows are those of the env without
    self-collision, bit for bit, and so are their sensing covariances; layout, projection
    and filter settings put the pairs between the two."""
    kwargs = {"nominal_model": "perturbed", "velocity_noise": 0.01, "position_noise": 0.001}
    on = FrankaObstacleEnv(**kwargs)  # on by default with the arm's spheres
    off = FrankaObstacleEnv(self_collision=False, **kwargs)
    assert on.self_collision and not off.self_collision
    rng = np.random.default_rng(5)
    q, qd = fm.Q_HOME + rng.uniform(-0.4, 0.4, 7), rng.uniform(-0.5, 0.5, 7)
    for env in (on, off):
        env.reset(seed=0)
        env.set_state(q, qd)
    rows, k, n_self = _self_rows(on), on.n_obstacle_barriers, on.n_self_collision_barriers
    assert n_self == len(sc.PANDA_SELF_COLLISION_PAIRS) and off.n_self_collision_barriers == 0
    assert on.n_barriers == off.n_barriers + n_self
    assert on.barrier_names == (off.barrier_names[:k] + tuple(
        f"{SPHERES[a].body[7:]}[{a}]/{SPHERES[b].body[7:]}[{b}]"
        for a, b in sc.PANDA_SELF_COLLISION_PAIRS) + off.barrier_names[k:])
    assert on.barrier_names[rows.stop - 1] == "link7[20]/link0[22]"
    others = np.r_[0:k, rows.stop:on.n_barriers]
    for model in ("nominal", "true"):
        a, b = on.barrier_terms(model), off.barrier_terms(model)
        for x, y in ((a.derivatives, b.derivatives), (a.lf, b.lf), (a.lg, b.lg), (a.xi, b.xi),
                     (a.covariance, b.covariance), (a.projection, b.projection)):
            np.testing.assert_array_equal(x[others], y)
    nominal, true = on.barrier_terms("nominal"), on.barrier_terms("true")
    lf, lg = _independent_terms(on.nominal_mj_model, on._sensed_view.data,
                                sc.PANDA_SELF_COLLISION_PAIRS)
    np.testing.assert_allclose(nominal.lf[rows], lf, rtol=1e-9, atol=1e-9 * np.abs(lf).max())
    np.testing.assert_allclose(nominal.lg[rows], lg, rtol=1e-9, atol=1e-9 * np.abs(lg).max())
    assert np.abs(true.lg[rows] - nominal.lg[rows]).max() > 1e-3  # the plant differs
    np.testing.assert_array_equal(nominal.derivatives, true.derivatives)
    # the features, the sensing covariance (encoders only) and the projection rows
    view, pairs = on._sensed_view, on._self_pairs
    np.testing.assert_allclose(pairs.fixed, _centres(on.model, mujoco.MjData(on.model),
                                                     q)[N_ARM:], rtol=0, atol=1e-15)
    p, v, jac, bias = _with_base(pairs, *view.spheres)
    first, second = pairs.first, pairs.second
    np.testing.assert_allclose(true.xi[rows, 14:17], p[first] - p[second], atol=1e-15)
    np.testing.assert_allclose(true.xi[rows, 17:20], v[first] - v[second], atol=1e-15)
    np.testing.assert_array_equal(true.xi[rows, :7], np.broadcast_to(view.data.qpos, (n_self, 7)))
    n = view.self_pairs.n
    grad = np.einsum("pi,pij->pj", n, jac[first] - jac[second])
    np.testing.assert_allclose(nominal.projection[rows], grad, atol=1e-15)
    gain = (grad ** 2).sum(axis=1)
    np.testing.assert_allclose(nominal.covariance[rows, 0, 0], 1e-6 * gain, rtol=1e-12)
    np.testing.assert_allclose(nominal.covariance[rows, 1, 1], 1e-4 * gain, rtol=1e-12)
    # the kinematic and zero models
    for model in ("kinematic", "zero"):
        env = FrankaObstacleEnv(self_collision=True, nominal_model=model)
        env.reset(seed=0)
        env.set_state(q, qd)
        t = env.barrier_terms("nominal")
        assert not t.lg[rows].any()
        if model == "zero":
            assert not t.lf[rows].any()
            continue
        p, v, _, bias = _with_base(pairs, *env._spheres)
        offset, vr, n = p[first] - p[second], v[first] - v[second], env._true_view.self_pairs.n
        np.testing.assert_allclose(n, offset / np.linalg.norm(offset, axis=1)[:, None],
                                   rtol=1e-12)
        curv = ((vr * vr).sum(1) - (n * vr).sum(1) ** 2) / np.linalg.norm(offset, axis=1)
        np.testing.assert_allclose(t.lf[rows], (n * (bias[first] - bias[second])).sum(1) + curv,
                                   rtol=1e-12, atol=1e-12)
    # layout and the filter's settings: the pairs' rows are the obstacle pairs'
    layout, shared = on.barrier_layout, on.shared_barrier_layout
    assert np.all(layout.relative_degree[: rows.stop] == 2)
    np.testing.assert_array_equal(layout.learner[rows], np.arange(k, rows.stop))
    assert np.all(shared.learner[: rows.stop] == -1)
    np.testing.assert_array_equal(layout.learner[rows.stop:] - n_self,
                                  off.barrier_layout.learner[k:])
    defaults = on.filter_defaults
    for key in ("activation_distance", "braking_deceleration", "first_gain"):
        np.testing.assert_array_equal(defaults[key][rows], defaults[key][0])
        np.testing.assert_array_equal(defaults[key][others], off.filter_defaults[key])
    assert set(defaults["calibration"][: rows.stop]) == {"off"}
    assert defaults["calibration"][rows.stop:] == off.filter_defaults["calibration"][k:]


def test_bad_input_is_refused_by_name():
    for value in ("yes", 1, 0.0):
        with pytest.raises(ValueError, match="self_collision must be True, False or None"):
            FrankaObstacleEnv(self_collision=value)
    with pytest.raises(ValueError, match="self_collision=True needs safety_spheres='arm'"):
        gym.make("afvsgp_gym/FrankaObstacleStatic-v0", self_collision=True,
                 safety_spheres="ee")
    with pytest.raises(ValueError, match=r"safety_spheres=\[\("):
        FrankaObstacleEnv(self_collision=True,
                          safety_spheres=[("panda0_link7", (0, 0, 0.2), 0.05)])


# --- the self-contact flag ---------------------------------------------------------------

def _geom_links(m, geoms):
    """The link of each collision geom from the body tree; the hand's mesh one further."""
    return {int(g): _chain_depth(m, int(m.geom_bodyid[g]))
            + (m.geom_dataid[g] >= 0 and m.mesh(m.geom_dataid[g]).name == "hand_col")
            for g in geoms}


def _touching(m, d, pairs):
    return any(mujoco.mj_geomDistance(m, d, a, b, 0.01, None) < 0 for a, b in pairs)


def _base_geoms(m) -> np.ndarray:
    """The base's (link0's) collision geoms: group 3, as the arm's."""
    return np.flatnonzero((m.geom_bodyid == m.body("panda0_link0").id) & (m.geom_group == 3))


@pytest.fixture(scope="module")
def contact_pairs():
    """Every pair of collision geoms of the base and the arm on links two apart, none
    touching at the ready pose (so none is left out)."""
    m = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    d = mujoco.MjData(m)
    base = _base_geoms(m)
    assert len(base) == 1
    np.testing.assert_array_equal(fm.base_collision_geoms(m), base)
    link = _geom_links(m, np.concatenate([base, fm.arm_collision_geoms(m)]))
    pairs = [(a, b) for a in link for b in link if a < b and abs(link[a] - link[b]) >= 2]
    d.qpos[:7] = fm.Q_HOME
    mujoco.mj_kinematics(m, d)
    assert not any(_touching(m, d, [pair]) for pair in pairs)
    return pairs


def test_self_contact_flag_equals_a_direct_check(contact_pairs):
    """Full random torques fold the arm onto itself and onto its base; the flag is the
    direct check of every pair at every step (the base's included: some steps touch only
    the base), and the folded pose is a contact, the ready pose not."""
    env = FrankaObstacleEnv()
    _, info = env.reset(seed=0)
    assert info["self_contact"] is False
    assert sorted(zip(env._self_contact_pairs.first, env._self_contact_pairs.second,
                      strict=True)) == sorted(contact_pairs)
    base = set(_base_geoms(env.model).tolist())
    arm_pairs = [(a, b) for a, b in contact_pairs if a not in base]
    rng = np.random.default_rng(0)
    flags, base_only = [], 0
    for _ in range(400):
        _, _, term, _, info = env.step(rng.uniform(-1.0, 1.0, 7))
        assert not term
        flags.append(info["self_contact"])
        assert flags[-1] == _touching(env.model, env.data, contact_pairs)
        assert info["cost"] == 1.0 or not flags[-1]  # self-contact is a cost
        base_only += flags[-1] and not _touching(env.model, env.data, arm_pairs)
    assert 20 < sum(flags) < 380 and base_only > 0
    env.set_state(FOLDED, np.zeros(7))
    _, _, _, _, info = env.step(np.zeros(7))
    assert info["self_contact"] and info["cost"] == 1.0 and not info["collision"]


def test_every_barrier_held_means_no_self_contact(contact_pairs):
    """In sampled configurations where every self-collision barrier holds (h >= 0), no two
    geoms touch beyond the spheres' coverage tolerance."""
    env = FrankaObstacleEnv(self_collision=True)
    env.reset(seed=0)
    m, d, rows = env.model, env.data, _self_rows(env)
    rng = np.random.default_rng(1)
    held = 0
    for _ in range(300):
        env.set_state(rng.uniform(m.jnt_range[:7, 0], m.jnt_range[:7, 1]), np.zeros(7))
        if env.barrier_values()[rows].min() >= 0:
            held += 1
            assert min(mujoco.mj_geomDistance(m, d, a, b, 1.0, None)
                       for a, b in contact_pairs) >= -COVERAGE_TOLERANCE
    assert held > 100


# --- the filter --------------------------------------------------------------------------

def _random_episode(filtered: bool, steps: int = 1500):
    env = gym.make("afvsgp_gym/FrankaObstacleStatic-v0", nominal_model="exact",
                   self_collision=True, max_episode_steps=steps)
    env = EpisodeSafetyStats(SafetyFilter(env, learner="oracle") if filtered else env)
    policy = make_policy("random", env, 0)
    obs, _ = env.reset(seed=0)
    rows, least = _self_rows(env.unwrapped), np.inf
    for _ in range(steps):
        obs, _, term, trunc, info = env.step(policy(obs))
        least = min(least, float(info["h_per_barrier"][rows].min()))
        assert not term
    assert trunc
    return info["episode_safety"]["self_contact_steps"], least


def test_oracle_filter_keeps_a_random_policy_off_itself():
    """Uniform random torques touch the arm to itself within 1500 steps (6 s); behind the
    oracle filter they never do, and no self-collision barrier goes below 0."""
    contacts, least = _random_episode(filtered=False)
    assert contacts > 50 and least < 0
    contacts, least = _random_episode(filtered=True)
    assert contacts == 0 and least >= 0


def test_the_self_collision_barriers_are_what_stops_a_fold():
    """A joint-space spring towards a pose with the fingers in link1 (inside the joint-limit
    barriers' margins): the oracle filter with the obstacle and limit barriers only lets it
    fold the arm onto itself; with the self-collision barriers it never touches."""
    counts = []
    for on in (False, True):
        env = SafetyFilter(gym.make("afvsgp_gym/FrankaObstacleStatic-v0",
                                    nominal_model="exact", self_collision=on),
                           learner="oracle")
        obs, _ = env.reset(seed=0)
        contacts, least = 0, np.inf
        for _ in range(600):
            q, qd = obs[:7].astype(np.float64), obs[7:14].astype(np.float64)
            obs, _, _, _, info = env.step(np.clip(3.0 * (FOLD_TARGET - q) - qd, -1.0, 1.0))
            contacts += info["self_contact"]
            if on:
                least = min(least, float(info["h_per_barrier"][_self_rows(env.unwrapped)].min()))
        counts.append(contacts)
    assert counts[0] > 100 and counts[1] == 0 and least >= 0
