"""Chance-constrained SOCP filter against independent references (scipy SLSQP, a dense grid,
closed forms), with any number of constraints per call, bad and non-finite input."""

import numpy as np
import pytest
from socp_reference import margins as _margins
from socp_reference import slsqp as _slsqp

from afvsgp_gym.cbf import SOCPFilter


def _random_instance(rng, m, K, feasible=True, cone=True):
    low, high = -rng.uniform(0.5, 2, m), rng.uniform(0.5, 2, m)
    a = rng.normal(size=(K, m))
    G = rng.normal(scale=0.3, size=(K, m + 1, m + 1)) if cone else None
    u_star = rng.uniform(low, high)
    base = _margins(u_star, np.zeros(K), a, G)
    slack = rng.uniform(0.05, 0.5, K) if feasible else -rng.uniform(5, 10, K)
    a0 = -base + slack
    u_nom = rng.uniform(2 * low, 2 * high)
    return low, high, u_nom, a0, a, G


@pytest.mark.parametrize("fast_path", [True, False])
@pytest.mark.parametrize("cone", [True, False])
@pytest.mark.parametrize("seed", range(12))
def test_random_instances_match_slsqp(seed, cone, fast_path):
    rng = np.random.default_rng(seed)
    m, K = int(rng.integers(2, 8)), int(rng.integers(1, 5))
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K, cone=cone)
    f = SOCPFilter(low, high, fast_path=fast_path)
    res = f.solve(u_nom, a0, a, G)
    assert res.feasible
    assert np.all(res.u >= low) and np.all(res.u <= high)
    scale = np.abs(a0) + np.abs(a) @ np.abs(res.u) + 1.0
    assert np.all(_margins(res.u, a0, a, G) >= -1e-8 * scale)
    ref = _slsqp(u_nom, a0, a, G, low, high)
    assert ref is not None
    f_ours = 0.5 * np.sum((res.u - u_nom) ** 2)
    assert f_ours <= ref.fun + 1e-7
    # strong convexity: |u - u*|^2 / 2 <= f(u_ref) - f(u*) for the feasible reference
    assert 0.5 * np.sum((res.u - ref.x) ** 2) <= ref.fun - f_ours + 1e-7
    # the solver objects are reused: another instance of the same size through the filter
    _, _, u_nom2, a02, a2, G2 = _random_instance(rng, m, K, cone=cone)
    res2 = f.solve(np.clip(u_nom2, low, high), a02 + 1.0, a2, G2)
    ref2 = _slsqp(np.clip(u_nom2, low, high), a02 + 1.0, a2, G2, low, high)
    if ref2 is not None:
        assert res2.feasible
        assert 0.5 * np.sum((res2.u - np.clip(u_nom2, low, high)) ** 2) <= ref2.fun + 1e-7


def test_matches_dense_grid_in_2d():
    rng = np.random.default_rng(42)
    low, high = -np.ones(2), np.ones(2)
    a0, a = np.array([-0.3]), np.array([[1.0, 0.5]])
    G = rng.normal(scale=0.2, size=(1, 3, 3))
    u_nom = np.array([-0.8, -0.6])
    g = np.linspace(-1, 1, 801)
    U = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    ubar = np.hstack([np.ones((len(U), 1)), U])
    marg = a0[0] + U @ a[0] - np.linalg.norm(ubar @ G[0].T, axis=1)
    cost = 0.5 * np.sum((U - u_nom) ** 2, axis=1)
    best = cost[marg >= 0].min()
    for fast_path in (True, False):
        res = SOCPFilter(low, high, fast_path=fast_path).solve(u_nom, a0, a, G)
        ours = 0.5 * np.sum((res.u - u_nom) ** 2)
        assert res.feasible and best - 5e-3 <= ours <= best + 1e-9


@pytest.mark.parametrize("seed", range(5))
def test_zero_sigma_equals_cbf_qp(seed):
    rng = np.random.default_rng(100 + seed)
    m, K = 3, 2
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K)
    f = SOCPFilter(low, high)
    r_cone = f.solve(u_nom, a0, a, np.zeros_like(G))
    r_qp = f.solve(u_nom, a0, a, None)
    r_clarabel = SOCPFilter(low, high, fast_path=False).solve(u_nom, a0, a, None)
    r_qpsolvers = SOCPFilter(low, high, qp_solver="clarabel", fast_path=False).solve(
        u_nom, a0, a, None
    )
    ref = _slsqp(u_nom, a0, a, None, low, high)
    for r in (r_cone, r_qp, r_clarabel, r_qpsolvers):
        assert r.feasible
        np.testing.assert_allclose(0.5 * np.sum((r.u - u_nom) ** 2), ref.fun, atol=1e-6)
        np.testing.assert_allclose(r.u, ref.x, atol=1e-4)
    np.testing.assert_array_equal(r_cone.u, r_qp.u)  # G = 0 is the QP, same path


def test_single_constraint_closed_form():
    # projection onto a half-space inside the box: u = u_nom + max(0, -(a0 + a u_nom)) a / |a|^2
    a0, a = np.array([-0.5]), np.array([[1.0, 2.0]])
    res = SOCPFilter(-10 * np.ones(2), 10 * np.ones(2)).solve(np.zeros(2), a0, a)
    assert res.status == "certified:halfspace"
    np.testing.assert_allclose(res.u, 0.5 * a[0] / 5.0, rtol=1e-15)


def test_inactive_returns_clipped_nominal_exactly():
    f = SOCPFilter(-np.ones(2), np.ones(2))
    res = f.solve(np.array([3.0, 0.2]), [1.0], [[0.0, 1.0]], np.zeros((1, 3, 3)))
    assert res.status == "inactive" and res.feasible
    np.testing.assert_array_equal(res.u, [1.0, 0.2])


def test_any_number_of_constraints_per_call():
    """k varies from call to call (0, 1, 7, 40, 2, 100, 0) through one filter; k = 0 returns
    the clipped proposal; every answer matches a fresh filter's and the reference's."""
    rng = np.random.default_rng(7)
    m = 7
    low, high = -np.ones(m), np.ones(m)
    f = SOCPFilter(low, high)
    for k in (0, 1, 7, 40, 2, 100, 0, 7):
        u_nom = rng.uniform(-1.5, 1.5, m)
        a = rng.normal(size=(k, m))
        a0 = -(a @ np.clip(u_nom, low, high)) + rng.uniform(-0.5, 3.0, k)
        for G in (None, 0.05 * rng.normal(size=(k, m + 1, m + 1))):
            res = f.solve(u_nom, a0, a, G)
            assert res.margins.shape == (k,)
            if k == 0:
                assert res.status == "inactive"
                np.testing.assert_array_equal(res.u, np.clip(u_nom, low, high))
                continue
            fresh = SOCPFilter(low, high).solve(u_nom, a0, a, G)
            assert res.feasible == fresh.feasible
            np.testing.assert_allclose(res.u, fresh.u, atol=1e-6)
            if res.feasible:
                ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(u_nom, a0, a, G)
                np.testing.assert_allclose(res.u, ref.u, atol=1e-5)


@pytest.mark.parametrize("seed", range(5))
def test_infeasible_gives_flagged_max_margin_fallback(seed):
    rng = np.random.default_rng(200 + seed)
    m, K = 2, 2
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K, feasible=False)
    for G_case in (G, None):
        res = SOCPFilter(low, high).solve(u_nom, a0, a, G_case)
        assert not res.feasible and res.status.startswith("fallback")
        assert np.all(np.isfinite(res.u)) and np.all(res.u >= low) and np.all(res.u <= high)
        g0 = np.linspace(low[0], high[0], 401)
        g1 = np.linspace(low[1], high[1], 401)
        U = np.stack(np.meshgrid(g0, g1), -1).reshape(-1, 2)
        worst = np.min([_margins_batch(U, a0[k], a[k], None if G_case is None else G_case[k])
                        for k in range(K)], axis=0)
        assert np.min(_margins(res.u, a0, a, G_case)) >= worst.max() - 1e-3


def _margins_batch(U, a0, a, G):
    out = a0 + U @ a
    if G is None:
        return out
    ubar = np.hstack([np.ones((len(U), 1)), U])
    return out - np.linalg.norm(ubar @ G.T, axis=1)


@pytest.mark.parametrize("seed", range(20))
def test_farkas_infeasibility_agrees_with_clarabel(seed):
    """A QP the fast path declares infeasible (Farkas certificate) is infeasible for clarabel
    too; a feasible one with a margin of 1e-6 is never declared infeasible."""
    rng = np.random.default_rng(300 + seed)
    m, k = 7, int(rng.integers(2, 30))
    low, high = -np.ones(m), np.ones(m)
    a = rng.normal(size=(k, m))
    u_star = rng.uniform(-1, 1, m)
    u_nom = rng.uniform(-1.5, 1.5, m)
    for shift in (-rng.uniform(0.5, 3.0), 1e-6):
        a0 = -(a @ u_star) + shift + np.where(np.arange(k) < 2, 0.0, 5.0)
        res = SOCPFilter(low, high).solve(u_nom, a0, a)
        ref = SOCPFilter(low, high, fast_path=False).solve(u_nom, a0, a)
        if res.status == "fallback:infeasible":
            assert ref.status.startswith("fallback:") and not ref.feasible
        if shift > 0:
            assert res.feasible and res.status != "fallback:infeasible"


def test_backup_only_evaluated_when_infeasible():
    calls = []

    def backup():
        calls.append(1)
        return np.array([0.3, -0.2])

    f = SOCPFilter(-np.ones(2), np.ones(2))
    feasible = f.solve(np.array([0.9, 0.9]), [-0.5], [[1.0, 0.0]], None, backup)
    assert feasible.feasible and not calls
    res = f.solve(np.zeros(2), [-5.0], [[1.0, 0.0]], None, backup)  # needs u0 >= 5
    assert calls == [1] and not res.feasible and res.status.startswith("backup:")
    np.testing.assert_array_equal(res.u, [0.3, -0.2])
    bad = f.solve(np.zeros(2), [-5.0], [[1.0, 0.0]], None, lambda: [np.nan, 0.0])
    assert bad.status.startswith("fallback:") and np.all(np.isfinite(bad.u))


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", ["u_nom", "a0", "a", "G"])
def test_non_finite_inputs_give_finite_flagged_action(where, value):
    low, high = -np.ones(3), np.ones(3)
    args = {
        "u_nom": np.array([0.5, -0.2, 0.1]),
        "a0": np.array([-0.1, 0.2]),
        "a": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
        "G": np.stack([0.1 * np.eye(4)] * 2),
    }
    args[where] = args[where].copy()
    args[where].flat[0] = value
    res = SOCPFilter(low, high).solve(**args)
    assert not res.feasible and res.status == "invalid_input"
    assert np.all(np.isfinite(res.u)) and np.all(res.u >= low) and np.all(res.u <= high)
    if where != "u_nom":  # the invalid constraint is left out, its margin is NaN
        assert np.isnan(res.margins[0]) and np.isfinite(res.margins[1])


def test_bad_shapes_and_construction():
    f = SOCPFilter(-np.ones(2), np.ones(2))
    with pytest.raises(ValueError, match="u_nom"):
        f.solve(np.zeros(3), [0.0], [[1.0, 0.0]])
    with pytest.raises(ValueError, match="a must have shape"):
        f.solve(np.zeros(2), [0.0, 1.0], [[1.0, 0.0]])
    with pytest.raises(ValueError, match="G must have shape"):
        f.solve(np.zeros(2), [0.0], [[1.0, 0.0]], np.zeros((1, 2, 2)))
    with pytest.raises(ValueError, match="action bounds"):
        SOCPFilter([1.0], [0.0])
    with pytest.raises(ValueError, match="same non-empty shape"):
        SOCPFilter([0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="n_constraints"):
        SOCPFilter([0.0], [1.0], -1)
    with pytest.raises(ValueError, match="qp_solver"):
        SOCPFilter([0.0], [1.0], qp_solver="no_such_solver")
    with pytest.raises(ValueError, match="tol"):
        SOCPFilter([0.0], [1.0], tol=0.0)


def _spy_cone_counts(f):
    """Record the number of cones of every clarabel program the filter solves (the real
    solver runs)."""
    sizes, solve = [], f.programs.solve

    def spy(kind, u_nom, a0, a, G=None):
        sizes.append(a0.size)
        return solve(kind, u_nom, a0, a, G)

    f.programs.solve = spy
    return sizes


@pytest.mark.parametrize("seed", range(10))
def test_many_cones_working_set_answer_is_the_whole_programs_optimum(seed):
    """With many cones clarabel solves working sets of them; the answer is the optimum of the
    whole program: clarabel on every cone at a tighter tolerance, and SLSQP."""
    rng = np.random.default_rng(500 + seed)
    m, K = 7, int(rng.integers(6, 16))
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K)
    u_nom = 3.0 * u_nom  # far outside: many cones violated at the proposal
    f = SOCPFilter(low, high)
    sizes = _spy_cone_counts(f)
    res = f.solve(u_nom, a0, a, G)
    ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(u_nom, a0, a, G)
    assert res.feasible and ref.feasible
    scale = np.abs(a0) + np.abs(a) @ np.abs(res.u) + np.abs(G).sum(axis=(1, 2))
    assert np.all(_margins(res.u, a0, a, G) >= -1e-8 * scale)
    # clarabel's answers are optimal to ~sqrt(tol) in u (1-strongly convex objective)
    np.testing.assert_allclose(res.u, ref.u, atol=1e-4)
    slsqp = _slsqp(u_nom, a0, a, G, low, high)
    if slsqp is not None:
        assert 0.5 * np.sum((res.u - u_nom) ** 2) <= slsqp.fun + 1e-7
    assert all(k <= K for k in sizes)


def test_working_sets_smaller_than_the_program_are_used():
    """Across random many-cone programs, some are answered by clarabel on fewer cones than
    the program has (the working set), and every answer matches the whole program's."""
    smaller = 0
    for seed in range(30):
        rng = np.random.default_rng(700 + seed)
        low, high, u_nom, a0, a, G = _random_instance(rng, 7, 12)
        f = SOCPFilter(low, high)
        sizes = _spy_cone_counts(f)
        res = f.solve(3.0 * u_nom, a0, a, G)
        ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(3.0 * u_nom, a0, a, G)
        assert res.feasible == ref.feasible
        if res.feasible:
            np.testing.assert_allclose(res.u, ref.u, atol=1e-4)
        smaller += bool(sizes) and min(sizes) < 12
    assert smaller >= 3


@pytest.mark.parametrize("seed", range(5))
def test_many_cones_infeasible_is_flagged_like_the_whole_program(seed):
    """Two contradicting cones among ten: infeasible, found on a working set, flagged as the
    whole program's clarabel solve flags it."""
    rng = np.random.default_rng(900 + seed)
    m, K = 7, 10
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K)
    a[1] = -a[0]
    G[1] = G[0]
    a0[0] = a0[1] = -0.05  # a0 + a u >= ||G ubar|| >= 0 and a0 - a u >= 0: no u
    res = SOCPFilter(low, high).solve(u_nom, a0, a, G)
    ref = SOCPFilter(low, high, fast_path=False).solve(u_nom, a0, a, G)
    assert not ref.feasible
    assert not res.feasible and res.status.startswith("fallback:")
    assert np.all(np.isfinite(res.u)) and np.all(res.u >= low) and np.all(res.u <= high)


def _spy_least_distance_sizes(monkeypatch):
    """Record the number of half-spaces of every least-distance (NNLS) solve."""
    from afvsgp_gym.cbf import fastpath

    sizes = []
    inner = fastpath.project_polyhedron_box

    def spy(u_nom, a0, a, low, high, norms=None):
        sizes.append(a0.size)
        return inner(u_nom, a0, a, low, high, norms)

    monkeypatch.setattr(fastpath, "project_polyhedron_box", spy)
    return sizes


@pytest.mark.parametrize("seed", range(12))
def test_qp_working_set_answer_is_the_whole_programs_optimum(seed, monkeypatch):
    """The QP's fast path solves the half-spaces violated at the clipped proposal (enlarged
    by those its answer violates); the certified answer is the whole program's optimum:
    clarabel on every half-space at a tight tolerance, and SLSQP; a Farkas verdict on a
    working set is also clarabel's."""
    rng = np.random.default_rng(900 + seed)
    m, K = 7, int(rng.integers(20, 60))
    low, high = -np.ones(m), np.ones(m)
    a = rng.normal(size=(K, m))
    u_star = rng.uniform(-0.5, 0.5, m)
    a0 = -(a @ u_star) + rng.uniform(0.0, 1.0, K)
    if seed % 4 == 3:  # two contradicting half-spaces among the others
        a[1] = -a[0]
        a0[1] = -a0[0] - 1.0
    u_nom = rng.uniform(-1.5, 1.5, m)
    sizes = _spy_least_distance_sizes(monkeypatch)
    res = SOCPFilter(low, high).solve(u_nom, a0, a)
    ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(u_nom, a0, a)
    assert res.feasible == ref.feasible
    if not res.feasible:
        assert res.status == "fallback:infeasible" and not ref.feasible
        return
    if res.status == "inactive":
        return
    assert res.status.startswith("certified:")
    assert np.all(a0 + a @ res.u >= -1e-12 * (np.abs(a0) + np.linalg.norm(a, axis=1) * 3))
    np.testing.assert_allclose(res.u, ref.u, atol=1e-5)
    slsqp = _slsqp(u_nom, a0, a, None, low, high)
    if slsqp is not None:
        assert 0.5 * np.sum((res.u - u_nom) ** 2) <= slsqp.fun + 1e-9
    assert all(s < K for s in sizes)


def test_qp_working_set_grows_and_stays_exact(monkeypatch):
    """Across random QPs some working sets are enlarged (the answer on the half-spaces
    violated at the clipped proposal violates another one); those answers equal clarabel's
    on the whole program."""
    grown = 0
    for seed in range(40):
        rng = np.random.default_rng(1100 + seed)
        m, K = 7, 30
        low, high = -np.ones(m), np.ones(m)
        a = rng.normal(size=(K, m))
        a0 = -(a @ rng.uniform(-0.3, 0.3, m)) + rng.uniform(0.0, 0.5, K)
        u_nom = rng.uniform(-2.0, 2.0, m)
        sizes = _spy_least_distance_sizes(monkeypatch)
        res = SOCPFilter(low, high).solve(u_nom, a0, a)
        if len(sizes) > 1:
            grown += 1
            assert sizes[1] > sizes[0] and res.status == "certified:polyhedron"
            ref = SOCPFilter(low, high, fast_path=False, tol=1e-11).solve(u_nom, a0, a)
            np.testing.assert_allclose(res.u, ref.u, atol=1e-5)
    assert grown >= 3


@pytest.mark.parametrize("kind", ["qp", "socp", "fallback_qp", "fallback_socp"])
def test_answer_does_not_depend_on_the_solver_object(kind):
    """A solver built ahead by ``prepare``, one reused across instances and one built for the
    instance give the same answer bit for bit (no data equilibration), for every size."""
    from afvsgp_gym.cbf.cone_programs import ConePrograms

    rng = np.random.default_rng(11)
    m = 4
    low, high = -np.ones(m), np.ones(m)
    prepared = ConePrograms(low, high, 1e-8, 1e-4)
    prepared.prepare(kind, range(1, 6))
    reused = ConePrograms(low, high, 1e-8, 1e-4)
    cone = kind.endswith("socp")
    for _ in range(3):
        for k in range(1, 6):
            _, _, u_nom, a0, a, G = _random_instance(rng, m, k, cone=cone)
            G = G if cone else None
            fresh = ConePrograms(low, high, 1e-8, 1e-4).solve(kind, u_nom, a0, a, G)
            for programs in (prepared, reused):
                x, status = programs.solve(kind, u_nom, a0, a, G)
                assert status == fresh[1]
                np.testing.assert_array_equal(x, fresh[0])
    with pytest.raises(ValueError, match="kind"):
        prepared.prepare("lp", [1])
    with pytest.raises(ValueError, match="sizes"):
        prepared.prepare(kind, [0])
