"""Weighted collapsed bound: direct formula, Titsias special case, finite-difference gradient."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from afvsgp_gym.gp.bound import weighted_bound, weighted_bound_and_grad
from afvsgp_gym.gp.kernels import ADPKernel


def _problem(seed, n=30, m_ind=6, b=3, m=2, phi=0.9):
    rng = np.random.default_rng(seed)
    kern = ADPKernel(rng.uniform(0.7, 2.0, (m + 1, b)), rng.uniform(0.5, 1.5, m + 1))
    xi, u = rng.normal(size=(n, b)), rng.normal(size=(n, m))
    z = np.sin(xi[:, 0]) + u[:, 0] * xi[:, 1] + 0.1 * rng.normal(size=n)
    w = phi ** np.arange(n)[::-1]
    return kern, xi, u, z, w, xi[:m_ind], u[:m_ind]


def _direct(kern, s2, xi, u, z, w, xo, uo):
    """DESIGN.md: log N(z|0, Q + s2 Lambda^-1) - (sum w - N)/2 log 2 pi s2 - trace/(2 s2),
    plus the constant -1/2 sum log w of the exact weighted ELBO."""
    koo = kern(xo, uo)
    kxo = kern(xi, u, xo, uo)
    q = kxo @ np.linalg.solve(koo, kxo.T)
    n = len(z)
    val = multivariate_normal(np.zeros(n), q + s2 * np.diag(1.0 / w)).logpdf(z)
    val -= (w.sum() - n) / 2 * np.log(2 * np.pi * s2)
    val -= 0.5 * np.sum(np.log(w))
    val -= np.sum(w * (kern.diag(xi, u) - np.diag(q))) / (2 * s2)
    return val


@pytest.mark.parametrize("phi", [1.0, 0.9])
def test_bound_matches_direct_formula(phi):
    kern, xi, u, z, w, xo, uo = _problem(0, phi=phi)
    terms = weighted_bound(kern, 0.05, xi, u, z, w, xo, uo)
    np.testing.assert_allclose(terms.total, _direct(kern, 0.05, xi, u, z, w, xo, uo),
                               rtol=1e-9)
    assert terms.trace_term <= 0.0


def test_titsias_bound_is_below_exact_marginal_likelihood_and_tight_at_full_set():
    kern, xi, u, z, w, xo, uo = _problem(1, phi=1.0)
    exact = multivariate_normal(np.zeros(len(z)), kern(xi, u) + 0.05 * np.eye(len(z))).logpdf(z)
    assert weighted_bound(kern, 0.05, xi, u, z, w, xo, uo).total < exact
    full = weighted_bound(kern, 0.05, xi, u, z, w, xi, u, jitter=1e-10).total
    np.testing.assert_allclose(full, exact, rtol=1e-6)


@pytest.mark.parametrize("phi", [1.0, 0.85])
def test_gradient_matches_finite_differences(phi):
    kern, xi, u, z, w, xo, uo = _problem(2, phi=phi)
    params = np.concatenate([kern.theta, [np.log(0.1)]])
    val, grad = weighted_bound_and_grad(params.copy(), kern.clone(), xi, u, z, w, xo, uo, 1e-8)
    ref = weighted_bound(kern, 0.1, xi, u, z, w, xo, uo, 1e-8).total
    np.testing.assert_allclose(val, ref, rtol=1e-12)
    eps = 1e-5
    fd = np.empty_like(params)
    for j in range(len(params)):
        e = np.zeros_like(params)
        e[j] = eps
        fp = weighted_bound_and_grad(params + e, kern.clone(), xi, u, z, w, xo, uo, 1e-8)[0]
        fm = weighted_bound_and_grad(params - e, kern.clone(), xi, u, z, w, xo, uo, 1e-8)[0]
        fd[j] = (fp - fm) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
