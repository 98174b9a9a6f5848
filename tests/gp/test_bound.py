"""Weighted collapsed bound: direct formula, Titsias special case, finite-difference gradient
(well-conditioned points; the ill-conditioned ones are in test_ill_conditioned.py).
Tolerances: tests/gp/tolerances.py (first-order rounding bounds)."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal
from tolerances import assert_within, central_difference, gamma, kernel_rtol

from afvsgp_gym.gp.bound import weighted_bound, weighted_bound_and_grad
from afvsgp_gym.gp.kernels import ADPKernel


def _problem(seed, n=30, m_ind=6, b=3, m=2, phi=0.9):
    rng = np.random.default_rng(seed)
    kern = ADPKernel(rng.uniform(0.7, 2.0, (m + 1, b)), rng.uniform(0.5, 1.5, m + 1))
    xi, u = rng.normal(size=(n, b)), rng.normal(size=(n, m))
    z = np.sin(xi[:, 0]) + u[:, 0] * xi[:, 1] + 0.1 * rng.normal(size=n)
    w = phi ** np.arange(n)[::-1]
    return kern, xi, u, z, w, xi[:m_ind], u[:m_ind]


def _direct(kern, s2, xi, u, z, w, xo, uo, jitter=0.0):
    """DESIGN.md: log N(z|0, Q + s2 Lambda^-1) - (sum w - N)/2 log 2 pi s2 - trace/(2 s2),
    plus the constant -1/2 sum log w of the exact weighted ELBO (N x N, scipy).

    Returns the value and a bound on its rounding error: ``Q`` through a solve with K_oo
    (``gamma(M) cond(K_oo)`` relative to ``|K_xo| |K_oo^-1| |K_ox|``), the Gaussian through a
    decomposition of ``C = Q + s2 Lambda^-1`` (``gamma(N) cond(C)`` on its log det and
    quadratic form)."""
    koo = kern(xo, uo) + jitter * np.eye(len(xo))
    kxo = kern(xi, u, xo, uo)
    q = kxo @ np.linalg.solve(koo, kxo.T)
    n = len(z)
    cov = q + s2 * np.diag(1.0 / w)
    val = multivariate_normal(np.zeros(n), cov).logpdf(z)
    val -= (w.sum() - n) / 2 * np.log(2 * np.pi * s2)
    val -= 0.5 * np.sum(np.log(w))
    val -= np.sum(w * (kern.diag(xi, u) - np.diag(q))) / (2 * s2)
    mag_q = np.abs(kxo) @ np.abs(np.linalg.inv(koo)) @ np.abs(kxo.T)
    err_q = gamma(len(xo)) * np.linalg.cond(koo) * mag_q
    c = np.linalg.cond(cov)
    quad = z @ np.linalg.solve(cov, z)
    err = (np.sum(w * np.diag(err_q)) / (2 * s2) + c * np.sum(np.abs(np.linalg.solve(cov, err_q)))
           + gamma(n) * c * (abs(quad) + n * abs(np.log(np.linalg.norm(cov, 2))) + n))
    return val, err


def _rounding(kern, s2, xi, u, z, w):
    """The whitened bound's rounding: the N-term sums of the fit and trace terms that cancel,
    and the kernel entries' rounding through them."""
    big = (w @ (z * z) + w @ kern.diag(xi, u)) / s2
    return (4 * gamma(len(z)) + kernel_rtol(kern, xi)) * big


@pytest.mark.parametrize("phi", [1.0, 0.9])
def test_bound_matches_direct_formula(phi):
    kern, xi, u, z, w, xo, uo = _problem(0, phi=phi)
    terms = weighted_bound(kern, 0.05, xi, u, z, w, xo, uo)
    ref, ref_err = _direct(kern, 0.05, xi, u, z, w, xo, uo)
    assert_within(terms.total, ref, ref_err + _rounding(kern, 0.05, xi, u, z, w), "bound")
    assert terms.trace_term <= 0.0


def test_titsias_bound_is_below_exact_marginal_likelihood_and_tight_at_full_set():
    """At Z = X the bound equals the exact log marginal likelihood up to the jitter eps:
    ``0 <= K - Q <= eps I`` moves the trace term by <= N eps / (2 s2) and the Gaussian term by
    <= eps (tr (K + s2 I)^-1 + |(K + s2 I)^-1 z|^2) / 2."""
    kern, xi, u, z, w, xo, uo = _problem(1, phi=1.0)
    s2, eps = 0.05, 1e-10
    kmat = kern(xi, u) + s2 * np.eye(len(z))
    exact = multivariate_normal(np.zeros(len(z)), kmat).logpdf(z)
    assert weighted_bound(kern, s2, xi, u, z, w, xo, uo).total < exact
    full = weighted_bound(kern, s2, xi, u, z, w, xi, u, jitter=eps).total
    alpha = np.linalg.solve(kmat, z)
    model = eps * (len(z) / (2 * s2) + 0.5 * (np.trace(np.linalg.inv(kmat)) + alpha @ alpha))
    exact_err = gamma(len(z)) * np.linalg.cond(kmat) * (abs(z @ alpha) + len(z))
    assert_within(full, exact, model + exact_err + _rounding(kern, s2, xi, u, z, w), "bound")


@pytest.mark.parametrize("phi", [1.0, 0.85])
def test_gradient_matches_finite_differences(phi):
    kern, xi, u, z, w, xo, uo = _problem(2, phi=phi)
    params = np.concatenate([kern.theta, [np.log(0.1)]])
    val, grad = weighted_bound_and_grad(params.copy(), kern.clone(), xi, u, z, w, xo, uo, 1e-8)
    ref = weighted_bound(kern, 0.1, xi, u, z, w, xo, uo, 1e-8).total
    assert_within(val, ref, _rounding(kern, 0.1, xi, u, z, w), "value")

    def fun(p):
        k = kern.with_theta(p[:-1])
        v = weighted_bound_and_grad(p, kern.clone(), xi, u, z, w, xo, uo, 1e-8)[0]
        return v, abs(v) + _rounding(k, np.exp(p[-1]), xi, u, z, w) / gamma(len(z))

    fd, err = central_difference(fun, params, 1e-4)
    assert_within(grad, fd, err, "gradient")
