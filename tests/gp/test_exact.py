"""ExactGP: batch formula, Cholesky row append, marginal likelihood gradient and fit.
Tolerances: tests/gp/tolerances.py (first-order rounding bounds)."""

import numpy as np
import pytest
from gp_batch_formulas import exact_affine, synthetic
from tolerances import (
    assert_within,
    central_difference,
    contraction_tolerance,
    exact_affine_tolerance,
    gamma,
)

from afvsgp_gym.gp import ADPKernel, ExactGP
from afvsgp_gym.gp.exact import log_marginal_likelihood


def _kernel():
    return ADPKernel(np.full((3, 3), 1.1), np.array([1.0, 0.5, 0.3]))


def test_predict_affine_matches_batch_formula_and_predict():
    rng = np.random.default_rng(0)
    xi, u, z, _ = synthetic(rng, 60)
    gp = ExactGP(_kernel(), 0.02).fit(xi, u, z, False)
    xs, us = rng.normal(size=(5, 3)), rng.uniform(-1, 1, (5, 2))
    k = gp.kernel_
    bref, sref = exact_affine(k.lengthscales, k.variances, 0.02, xi, u, z, xs)
    bvec, sig = gp.predict_affine(xs)
    tol_b, tol_s = exact_affine_tolerance(gp, xs)  # the reference inverts K + s2 I
    assert_within(bvec, bref, tol_b, "b")
    assert_within(sig, sref, tol_s, "Sigma")
    mean, var = gp.predict(xs, us)
    ub = np.hstack([np.ones((5, 1)), us])
    tm, tv = contraction_tolerance(ub, tol_b, tol_s, bvec, sig)
    assert_within(mean, np.einsum("ni,ni->n", bvec, ub), tm, "mean")
    assert_within(var, np.einsum("ni,nij,nj->n", ub, sig, ub), tv, "variance")


def test_row_append_equals_refit_and_offline_mode_freezes():
    rng = np.random.default_rng(1)
    xi, u, z, _ = synthetic(rng, 80)
    gp = ExactGP(_kernel(), 0.02).fit(xi[:50], u[:50], z[:50], False)
    off = ExactGP(_kernel(), 0.02, online=False).fit(xi[:50], u[:50], z[:50], False)
    before = off.predict_affine(xi[:3])
    for i in range(50, 80):
        gp.update(xi[i], u[i], z[i])
        off.update(xi[i], u[i], z[i])
    ref = ExactGP(_kernel(), 0.02).fit(xi, u, z, False)
    # a row append is a backward-stable step (gamma(N + 1) |L| |L'| each); the factor then
    # moves by at most cond(K + s2 I) times the relative backward error
    kmat = ref.L_ @ ref.L_.T
    back = 30 * gamma(81) * np.max(np.abs(ref.L_) @ np.abs(ref.L_.T))
    rel = np.linalg.cond(kmat) * back / np.linalg.norm(kmat, 2)
    assert_within(gp.L_, ref.L_, 2 * rel * np.max(np.abs(ref.L_)), "L")
    tol_b, _ = exact_affine_tolerance(ref, xi[:3])
    assert_within(gp.predict_affine(xi[:3])[0], ref.predict_affine(xi[:3])[0],
                  tol_b + np.linalg.cond(kmat) * back / np.linalg.norm(kmat, 2)
                  * np.max(np.abs(ref.predict_affine(xi[:3])[0])), "b")
    for got, old in zip(off.predict_affine(xi[:3]), before, strict=True):
        np.testing.assert_array_equal(got, old)


@pytest.mark.parametrize("seed", [2])
def test_log_marginal_likelihood_gradient_finite_differences(seed):
    rng = np.random.default_rng(seed)
    xi, u, z, _ = synthetic(rng, 25)
    k = _kernel()
    p = np.concatenate([k.theta, [np.log(0.05)]])
    _, grad = log_marginal_likelihood(p.copy(), k.clone(), xi, u, z)

    def fun(q):  # value and the magnitude of what it sums (quadratic form, log det, const)
        val = log_marginal_likelihood(q, k.clone(), xi, u, z)[0]
        return val, abs(val) + len(z) * abs(np.log(np.exp(q[-1]))) + len(z)

    fd, err = central_difference(fun, p, 1e-4)
    assert_within(grad, fd, err + gamma(len(z)) * np.abs(grad), "gradient")


def test_fit_increases_likelihood_and_recovers_noise():
    rng = np.random.default_rng(3)
    xi, u, z, _ = synthetic(rng, 100, noise_std=0.2)
    gp0 = ExactGP().fit(xi, u, z, learn_hyperparameters=False)
    gp = ExactGP(max_iter=100).fit(xi, u, z)
    assert (gp.log_marginal_likelihood_value_ > gp0.log_marginal_likelihood_value_
            + gamma(100) * abs(gp0.log_marginal_likelihood_value_))
    assert 0.02 < gp.noise_variance_ < 0.06  # noise std 0.2: variance 0.04 within +-50 %
