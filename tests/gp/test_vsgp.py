"""VSGP: batch Titsias posterior, equivalence with the exact GP at Z = X, predict vs affine."""

import numpy as np
from gp_batch_formulas import synthetic, weighted_titsias_affine

from afvsgp_gym.gp import VSGP, ADPKernel, ExactGP


def _rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def _kernel():
    return ADPKernel(np.full((3, 3), 1.2), np.array([1.0, 0.5, 0.3]))


def test_update_refreshes_over_all_data_seen():
    rng = np.random.default_rng(0)
    xi, u, z, _ = synthetic(rng, 120)
    gp = VSGP(_kernel(), 0.01, num_inducing=10).fit(xi[:40], u[:40], z[:40], False)
    for i in range(40, 120):
        gp.update(xi[i], u[i], z[i])
    assert gp.n_seen_ == 120
    k = gp.kernel_
    xs = rng.normal(size=(4, 3))
    bref, sref = weighted_titsias_affine(k.lengthscales, k.variances, 0.01, xi, u, z,
                                         np.ones(120), gp.inducing_xi_, gp.inducing_u_, xs,
                                         jitter=gp.jitter_)
    bvec, sig = gp.predict_affine(xs)
    assert _rel(bvec, bref) < 1e-8 and _rel(sig, sref) < 1e-8


def test_inducing_at_all_inputs_equals_exact_gp():
    rng = np.random.default_rng(1)
    xi, u, z, _ = synthetic(rng, 50)
    v = VSGP(_kernel(), 0.05, inducing=(xi, u), jitter=0.0).fit(xi, u, z, False)
    e = ExactGP(_kernel(), 0.05).fit(xi, u, z, False)
    xs, us = rng.normal(size=(7, 3)), rng.uniform(-1, 1, (7, 2))
    for got, ref in zip(v.predict(xs, us), e.predict(xs, us), strict=True):
        assert _rel(got, ref) < 1e-6
    for got, ref in zip(v.predict_affine(xs), e.predict_affine(xs), strict=True):
        assert _rel(got, ref) < 1e-6


def test_predict_affine_agrees_with_predict_and_sigma_is_psd():
    rng = np.random.default_rng(2)
    xi, u, z, _ = synthetic(rng, 150)
    gp = VSGP(num_inducing=15).fit(xi, u, z)
    xs, us = rng.normal(size=(9, 3)), rng.uniform(-1, 1, (9, 2))
    mean, var = gp.predict(xs, us)
    bvec, sig = gp.predict_affine(xs)
    ub = np.hstack([np.ones((9, 1)), us])
    np.testing.assert_allclose(np.einsum("ni,ni->n", bvec, ub), mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ni,nij,nj->n", ub, sig, ub), var, rtol=1e-6,
                               atol=1e-10)
    np.testing.assert_array_equal(sig, sig.transpose(0, 2, 1))
    assert np.linalg.eigvalsh(sig).min() > -1e-10
    one_b, one_s = gp.predict_affine(xs[:1])  # single-point fast path
    np.testing.assert_allclose(one_b, bvec[:1], rtol=1e-12)
    np.testing.assert_allclose(one_s, sig[:1], rtol=1e-8, atol=1e-11)


def test_fit_increases_bound_and_recovers_noise():
    rng = np.random.default_rng(3)
    xi, u, z, _ = synthetic(rng, 300, noise_std=0.2)
    from afvsgp_gym.gp.bound import weighted_bound

    gp0 = VSGP(num_inducing=20).fit(xi, u, z, learn_hyperparameters=False)
    gp = VSGP(num_inducing=20).fit(xi, u, z)
    b0 = weighted_bound(gp0.kernel_, gp0.noise_variance_, xi, u, z, np.ones(300),
                        gp0.inducing_xi_, gp0.inducing_u_, gp0.jitter_).total
    assert gp.bound_ > b0
    assert 0.02 < gp.noise_variance_ < 0.06
