"""VSGP: batch Titsias posterior, equivalence with the exact GP at Z = X, predict vs affine.
Tolerances: tests/gp/tolerances.py (first-order rounding bounds)."""

import numpy as np
from gp_batch_formulas import synthetic, weighted_titsias_affine
from tolerances import (
    assert_within,
    contraction_tolerance,
    exact_affine_tolerance,
    gamma,
    sparse_affine_tolerance,
)

from afvsgp_gym.gp import VSGP, ADPKernel, ExactGP
from afvsgp_gym.gp.bound import weighted_bound


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
    tol_b, tol_s = sparse_affine_tolerance(gp, xs, (xi, u, z, np.ones(120)))
    assert_within(bvec, bref, tol_b, "b")
    assert_within(sig, sref, tol_s, "Sigma")


def test_inducing_at_all_inputs_equals_exact_gp():
    """Z = X without jitter: the Titsias posterior is the exact one. Both are backward stable
    for their own matrices (K_oo + S/s2 = K (K + s2 I) K / s2 here), so the sum of both
    learners' rounding bounds applies."""
    rng = np.random.default_rng(1)
    xi, u, z, _ = synthetic(rng, 50)
    v = VSGP(_kernel(), 0.05, inducing=(xi, u), jitter=0.0).fit(xi, u, z, False)
    e = ExactGP(_kernel(), 0.05).fit(xi, u, z, False)
    xs, us = rng.normal(size=(7, 3)), rng.uniform(-1, 1, (7, 2))
    tv = sparse_affine_tolerance(v, xs, (xi, u, z, np.ones(50)))
    te = exact_affine_tolerance(e, xs)
    for got, ref, t1, t2, what in zip(v.predict_affine(xs), e.predict_affine(xs), tv, te,
                                       ("b", "Sigma"), strict=True):
        assert_within(got, ref, t1 + t2, what)
    ub = np.hstack([np.ones((7, 1)), us])
    bvec, sig = e.predict_affine(xs)
    tm, tvar = contraction_tolerance(ub, tv[0] + te[0], tv[1] + te[1], bvec, sig)
    for got, ref, tol in zip(v.predict(xs, us), e.predict(xs, us), (tm, tvar), strict=True):
        assert_within(got, ref, tol, "predict")


def test_predict_affine_agrees_with_predict_and_sigma_is_psd():
    rng = np.random.default_rng(2)
    xi, u, z, _ = synthetic(rng, 150)
    gp = VSGP(num_inducing=15).fit(xi, u, z)
    xs, us = rng.normal(size=(9, 3)), rng.uniform(-1, 1, (9, 2))
    mean, var = gp.predict(xs, us)
    bvec, sig = gp.predict_affine(xs)
    ub = np.hstack([np.ones((9, 1)), us])
    # predict and predict_affine share the factors: only the contraction order differs
    tol_b, tol_s = sparse_affine_tolerance(gp, xs)
    tm, tv = contraction_tolerance(ub, tol_b, tol_s, bvec, sig)
    assert_within(np.einsum("ni,ni->n", bvec, ub), mean, tm, "mean")
    assert_within(np.einsum("ni,nij,nj->n", ub, sig, ub), var, tv, "variance")
    np.testing.assert_array_equal(sig, sig.transpose(0, 2, 1))
    # PSD up to the rounding of its three cancelling terms
    assert np.linalg.eigvalsh(sig).min() >= -np.max(np.abs(tol_s)) * 3
    one_b, one_s = gp.predict_affine(xs[:1])  # single-point path: same factors, same algebra
    assert_within(one_b, bvec[:1], tol_b[:1], "one-point b")
    assert_within(one_s, sig[:1], tol_s[:1], "one-point Sigma")


def test_fit_increases_bound_and_recovers_noise():
    rng = np.random.default_rng(3)
    xi, u, z, _ = synthetic(rng, 300, noise_std=0.2)
    gp0 = VSGP(num_inducing=20).fit(xi, u, z, learn_hyperparameters=False)
    gp = VSGP(num_inducing=20).fit(xi, u, z)
    b0 = weighted_bound(gp0.kernel_, gp0.noise_variance_, xi, u, z, np.ones(300),
                        gp0.inducing_xi_, gp0.inducing_u_, gp0.jitter_).total
    assert gp.bound_ > b0 + gamma(300) * abs(b0)
    assert 0.02 < gp.noise_variance_ < 0.06  # noise std 0.2: variance 0.04 within +-50 %
