"""Early exit of the filter: a safe (clipped) proposal is returned as is, and it is the SOCP
optimum (checked against the full cone solve)."""

import numpy as np
import pytest

from afvsgp_gym.cbf import SafetyController, SOCPFilter
from afvsgp_gym.types import BarrierTerms


def _margins(u, a0, a, G):
    ubar = np.concatenate([[1.0], u])
    return a0 + a @ u - np.linalg.norm(G @ ubar, axis=-1)


def _safe_instance(rng, m, K):
    """Random instance whose clipped proposal satisfies every cone with slack."""
    low, high = -rng.uniform(0.5, 2, m), rng.uniform(0.5, 2, m)
    a = rng.normal(size=(K, m))
    G = rng.normal(scale=0.3, size=(K, m + 1, m + 1))
    u_nom = rng.uniform(1.5 * low, 1.5 * high)
    uc = np.clip(u_nom, low, high)
    a0 = -_margins(uc, np.zeros(K), a, G) + rng.uniform(1e-3, 0.5, K)
    return low, high, u_nom, a0, a, G


@pytest.mark.parametrize("seed", range(10))
def test_early_exit_is_the_socp_optimum(seed):
    rng = np.random.default_rng(seed)
    m, K = int(rng.integers(2, 8)), int(rng.integers(1, 4))
    low, high, u_nom, a0, a, G = _safe_instance(rng, m, K)
    f = SOCPFilter(low, high, K)
    res = f.solve(u_nom, a0, a, G)
    assert res.status == "inactive" and res.feasible
    np.testing.assert_array_equal(res.u, np.clip(u_nom, low, high))
    # the full cone program on the same data (no early exit) gives the same action
    x, status = f.programs.solve("socp", u_nom, a0, a, G)
    assert status in ("Solved", "AlmostSolved")
    # feasible and no worse than the solver's optimum (its 1e-9 gap tolerance leaves ~1e-6
    # in x where a bound is active), so the early exit is the optimum itself
    f_exit, f_full = 0.5 * np.sum((res.u - u_nom) ** 2), 0.5 * np.sum((x[:m] - u_nom) ** 2)
    assert f_exit <= f_full + 1e-9
    assert f_full - f_exit <= 1e-6
    np.testing.assert_allclose(res.u, x[:m], atol=1e-5)
    assert np.all(_margins(res.u, a0, a, G) >= 0)


@pytest.mark.parametrize("seed", range(6))
def test_controller_matches_plain_solve(seed):
    """SafetyController.filter (fast path) returns what SOCPFilter.solve returns on the HOCBF
    constraints worked out by hand, with ``active`` False exactly when the proposal is
    returned unchanged."""
    rng = np.random.default_rng(200 + seed)
    m = 3
    ctrl = SafetyController(
        -np.ones(m), np.ones(m), 2, learner="none", alpha=2.0, activation_distance=np.inf
    )
    ref = SOCPFilter(-np.ones(m), np.ones(m), 2)
    for _ in range(20):
        terms = [
            BarrierTerms(
                rng.uniform([0.0, -1.0], [0.5, 1.0]),
                float(rng.normal()),
                rng.normal(size=m),
                rng.normal(size=4),
            )
            for _ in range(2)
        ]
        u_nom = rng.uniform(-1.5, 1.5, m)
        res = ctrl.filter(u_nom, terms)
        # by hand, alpha = 2 for both gains: psi_2 = lf + lg u + 4 h' + 4 h >= 0, less the
        # barrier margin 1e-3 times d psi_2 / d h = 4
        a0 = np.array([t.lf + 4.0 * t.derivatives[1] + 4.0 * t.derivatives[0] - 4e-3
                       for t in terms])
        a = np.array([t.lg for t in terms])
        r = ref.solve(u_nom, a0, a)
        assert res.status == r.status
        # the same program up to the rounding of a0 (summed in another order): a few ulps
        np.testing.assert_allclose(res.u, r.u, rtol=0, atol=1e-12)
        assert res.active == (r.status != "inactive")
        if not res.active:
            np.testing.assert_array_equal(res.u, np.clip(u_nom, -1, 1))


@pytest.mark.parametrize("seed", range(8))
def test_cone_matrix_factors_the_covariance(seed):
    """``||G ubar|| = beta sqrt(ubar' Sigma ubar)`` for positive definite (Cholesky), singular
    and rounding-level indefinite (eigen-factor) Sigma, against the quadratic form."""
    from afvsgp_gym.cbf.controller import cone_matrix

    rng = np.random.default_rng(300 + seed)
    m = 7
    for trial in range(50):
        rank = int(rng.integers(1, m + 2))
        L = rng.normal(scale=10.0 ** rng.uniform(-4, 1), size=(m + 1, rank))
        sig = L @ L.T
        if trial % 4 == 0:  # rounding-level indefiniteness
            sig = sig - 1e-14 * np.trace(sig) * np.eye(m + 1)
        beta = rng.uniform(0.5, 4.0)
        G = cone_matrix(sig, beta)
        assert G.shape == (m + 1, m + 1) and np.all(np.isfinite(G))
        np.testing.assert_allclose(G.T @ G, beta**2 * sig, atol=1e-9 * beta**2 * np.abs(sig).max())
        for ubar in rng.normal(size=(5, m + 1)):
            want = beta * np.sqrt(max(ubar @ sig @ ubar, 0.0))
            got = np.linalg.norm(G @ ubar)
            assert got == pytest.approx(want, rel=1e-6, abs=1e-7 * beta * np.sqrt(np.trace(sig)))


@pytest.mark.parametrize("seed", range(4))
def test_cone_matrices_equal_cone_matrix_row_by_row(seed):
    """The batched factor equals the one-at-a-time one (Cholesky rows), and a stack with an
    indefinite member falls back to the eigen-factor for every member."""
    from afvsgp_gym.cbf.controller import cone_matrices, cone_matrix

    rng = np.random.default_rng(700 + seed)
    L = rng.normal(size=(6, 8, 8))
    sig = L @ L.transpose(0, 2, 1)
    got = cone_matrices(sig, 2.5)
    want = np.array([cone_matrix(s, 2.5) for s in sig])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    sig[2] = sig[2] - 2.0 * np.linalg.eigvalsh(sig[2]).max() * np.eye(8)  # indefinite
    got = cone_matrices(sig, 2.5)
    assert np.all(np.isfinite(got))
    for g, s in zip(got, sig, strict=True):
        w = np.linalg.eigvalsh(0.5 * (s + s.T))
        np.testing.assert_allclose(np.linalg.eigvalsh(g.T @ g), 6.25 * np.maximum(w, 0.0),
                                   atol=1e-9 * 6.25 * np.abs(w).max())
