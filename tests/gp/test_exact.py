"""ExactGP: batch formula, Cholesky row append, marginal likelihood gradient and fit."""

import numpy as np
import pytest
from gp_batch_formulas import exact_affine, synthetic

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
    np.testing.assert_allclose(bvec, bref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(sig, sref, rtol=1e-8, atol=1e-10)
    mean, var = gp.predict(xs, us)
    ub = np.hstack([np.ones((5, 1)), us])
    np.testing.assert_allclose(mean, np.einsum("ni,ni->n", bvec, ub), rtol=1e-10)
    np.testing.assert_allclose(var, np.einsum("ni,nij,nj->n", ub, sig, ub), rtol=1e-8)


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
    np.testing.assert_allclose(gp.L_, ref.L_, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gp.predict_affine(xi[:3])[0], ref.predict_affine(xi[:3])[0],
                               rtol=1e-9)
    for got, old in zip(off.predict_affine(xi[:3]), before, strict=True):
        np.testing.assert_array_equal(got, old)


@pytest.mark.parametrize("seed", [2])
def test_log_marginal_likelihood_gradient_finite_differences(seed):
    rng = np.random.default_rng(seed)
    xi, u, z, _ = synthetic(rng, 25)
    k = _kernel()
    p = np.concatenate([k.theta, [np.log(0.05)]])
    _, grad = log_marginal_likelihood(p.copy(), k.clone(), xi, u, z)
    eps = 1e-5
    fd = np.array([(log_marginal_likelihood(p + eps * e, k.clone(), xi, u, z)[0]
                    - log_marginal_likelihood(p - eps * e, k.clone(), xi, u, z)[0]) / (2 * eps)
                   for e in np.eye(len(p))])
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_fit_increases_likelihood_and_recovers_noise():
    rng = np.random.default_rng(3)
    xi, u, z, _ = synthetic(rng, 100, noise_std=0.2)
    gp0 = ExactGP().fit(xi, u, z, learn_hyperparameters=False)
    gp = ExactGP(max_iter=100).fit(xi, u, z)
    assert gp.log_marginal_likelihood_value_ > gp0.log_marginal_likelihood_value_
    assert 0.02 < gp.noise_variance_ < 0.06
