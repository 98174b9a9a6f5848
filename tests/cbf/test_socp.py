"""Chance-constrained SOCP against an independent solver (scipy SLSQP) and a dense grid."""

import numpy as np
import pytest
from scipy.optimize import minimize

from afvsgp_gym.cbf import SOCPFilter


def _margins(u, a0, a, G):
    ubar = np.concatenate([[1.0], u])
    return a0 + a @ u - np.linalg.norm(G @ ubar, axis=-1)


def _random_instance(rng, m, K, feasible=True):
    low, high = -rng.uniform(0.5, 2, m), rng.uniform(0.5, 2, m)
    a = rng.normal(size=(K, m))
    G = rng.normal(scale=0.3, size=(K, m + 1, m + 1))
    u_star = rng.uniform(low, high)
    base = a @ u_star - np.linalg.norm(G @ np.concatenate([[1.0], u_star]), axis=-1)
    slack = rng.uniform(0.05, 0.5, K) if feasible else -rng.uniform(5, 10, K)
    a0 = -base + slack
    u_nom = rng.uniform(2 * low, 2 * high)
    return low, high, u_nom, a0, a, G


def _slsqp(u_nom, a0, a, G, low, high):
    cons = [
        {
            "type": "ineq",
            "fun": lambda u, k=k: _margins(u, a0[k : k + 1], a[k : k + 1], G[k : k + 1])[0],
        }
        for k in range(len(a0))
    ]
    best = None
    for x0 in [np.clip(u_nom, low, high), 0.5 * (low + high)]:
        r = minimize(
            lambda u: 0.5 * np.sum((u - u_nom) ** 2),
            x0,
            jac=lambda u: u - u_nom,
            bounds=list(zip(low, high, strict=True)),
            constraints=cons,
            method="SLSQP",
            options={"ftol": 1e-14, "maxiter": 500},
        )
        ok = np.all(_margins(r.x, a0, a, G) >= -1e-8)
        if ok and (best is None or r.fun < best.fun):
            best = r
    return best


@pytest.mark.parametrize("seed", range(12))
def test_random_instances_match_slsqp(seed):
    rng = np.random.default_rng(seed)
    m, K = int(rng.integers(2, 5)), int(rng.integers(1, 4))
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K)
    f = SOCPFilter(low, high, K)
    res = f.solve(u_nom, a0, a, G)
    assert res.feasible
    assert np.all(res.u >= low) and np.all(res.u <= high)
    assert np.all(_margins(res.u, a0, a, G) >= -1e-6)
    ref = _slsqp(u_nom, a0, a, G, low, high)
    assert ref is not None
    f_ours = 0.5 * np.sum((res.u - u_nom) ** 2)
    assert f_ours <= ref.fun + 1e-6
    np.testing.assert_allclose(res.u, ref.x, atol=1e-4)
    # the solver object is reused: a second instance of the same size through the same filter
    _, _, u_nom2, a02, a2, G2 = _random_instance(rng, m, K)
    a02 = a02 + 1.0
    res2 = f.solve(np.clip(u_nom2, low, high), a02, a2, G2)
    ref2 = _slsqp(np.clip(u_nom2, low, high), a02, a2, G2, low, high)
    if ref2 is not None:
        assert res2.feasible
        assert 0.5 * np.sum((res2.u - np.clip(u_nom2, low, high)) ** 2) <= ref2.fun + 1e-6


def test_matches_dense_grid_in_2d():
    rng = np.random.default_rng(42)
    low, high = -np.ones(2), np.ones(2)
    a0, a = np.array([-0.3]), np.array([[1.0, 0.5]])
    G = rng.normal(scale=0.2, size=(1, 3, 3))
    u_nom = np.array([-0.8, -0.6])
    res = SOCPFilter(low, high, 1).solve(u_nom, a0, a, G)
    g = np.linspace(-1, 1, 801)
    U = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    ubar = np.hstack([np.ones((len(U), 1)), U])
    marg = a0[0] + U @ a[0] - np.linalg.norm(ubar @ G[0].T, axis=1)
    cost = 0.5 * np.sum((U - u_nom) ** 2, axis=1)
    best = cost[marg >= 0].min()
    ours = 0.5 * np.sum((res.u - u_nom) ** 2)
    assert res.feasible and ours <= best + 1e-9 and ours >= best - 5e-3


@pytest.mark.parametrize("seed", range(5))
def test_zero_sigma_equals_cbf_qp(seed):
    rng = np.random.default_rng(100 + seed)
    m, K = 3, 2
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K)
    f = SOCPFilter(low, high, K)
    r_cone = f.solve(u_nom, a0, a, np.zeros_like(G))
    r_qp = f.solve(u_nom, a0, a, None)
    r_qpsolvers = SOCPFilter(low, high, K, qp_solver="clarabel").solve(u_nom, a0, a, None)
    ref = _slsqp(u_nom, a0, a, np.zeros_like(G), low, high)
    for r in (r_cone, r_qp, r_qpsolvers):
        assert r.feasible
        np.testing.assert_allclose(0.5 * np.sum((r.u - u_nom) ** 2), ref.fun, atol=1e-6)
        np.testing.assert_allclose(r.u, ref.x, atol=1e-4)


def test_single_constraint_closed_form():
    # projection onto a half-space, inside the box: u = u_nom + max(0, -(a0 + a u_nom)) a / |a|^2
    a0, a = np.array([-0.5]), np.array([[1.0, 2.0]])
    u_nom = np.array([0.0, 0.0])
    res = SOCPFilter(-10 * np.ones(2), 10 * np.ones(2), 1).solve(u_nom, a0, a)
    np.testing.assert_allclose(res.u, 0.5 * a[0] / 5.0, atol=1e-7)
    assert res.active if hasattr(res, "active") else res.status != "inactive"


def test_inactive_returns_clipped_nominal_exactly():
    f = SOCPFilter(-np.ones(2), np.ones(2), 1)
    res = f.solve(np.array([3.0, 0.2]), [1.0], [[0.0, 1.0]], np.zeros((1, 3, 3)))
    assert res.status == "inactive" and res.feasible
    np.testing.assert_array_equal(res.u, [1.0, 0.2])


@pytest.mark.parametrize("seed", range(5))
def test_infeasible_gives_flagged_max_margin_fallback(seed):
    rng = np.random.default_rng(200 + seed)
    m, K = 2, 2
    low, high, u_nom, a0, a, G = _random_instance(rng, m, K, feasible=False)
    res = SOCPFilter(low, high, K).solve(u_nom, a0, a, G)
    assert not res.feasible and res.status.startswith("fallback")
    assert np.all(np.isfinite(res.u)) and np.all(res.u >= low) and np.all(res.u <= high)
    g0 = np.linspace(low[0], high[0], 401)
    g1 = np.linspace(low[1], high[1], 401)
    U = np.stack(np.meshgrid(g0, g1), -1).reshape(-1, 2)
    worst = np.min([_margins_batch(U, a0[k], a[k], G[k]) for k in range(K)], axis=0)
    ours = np.min(_margins(res.u, a0, a, G))
    assert ours >= worst.max() - 1e-3


def _margins_batch(U, a0, a, G):
    ubar = np.hstack([np.ones((len(U), 1)), U])
    return a0 + U @ a - np.linalg.norm(ubar @ G.T, axis=1)


@pytest.mark.parametrize("where", ["u_nom", "a0", "a", "G"])
def test_nan_inputs_give_finite_flagged_action(where):
    low, high = -np.ones(3), np.ones(3)
    args = {
        "u_nom": np.array([0.5, -0.2, 0.1]),
        "a0": np.array([0.1]),
        "a": np.array([[1.0, 0.0, 0.0]]),
        "G": 0.1 * np.eye(4)[None],
    }
    args[where] = np.full_like(args[where], np.nan)
    res = SOCPFilter(low, high, 1).solve(**args)
    assert not res.feasible and res.status == "invalid_input"
    assert np.all(np.isfinite(res.u)) and np.all(res.u >= low) and np.all(res.u <= high)


def test_bad_construction():
    with pytest.raises(ValueError, match="action bounds"):
        SOCPFilter([1.0], [0.0])
    with pytest.raises(ValueError, match="same non-empty shape"):
        SOCPFilter([0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="n_constraints"):
        SOCPFilter([0.0], [1.0], 0)
    with pytest.raises(ValueError, match="qp_solver"):
        SOCPFilter([0.0], [1.0], qp_solver="no_such_solver")
