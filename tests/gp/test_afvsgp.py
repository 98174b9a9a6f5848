"""AFVSGP: equivalence with VSGP and with the batch weighted Titsias posterior, inducing-set
bookkeeping, hyperparameter fit and non-stationarity (paper Table I in miniature).
Tolerances: tests/gp/tolerances.py (first-order rounding bounds)."""

import numpy as np
import pytest
from gp_batch_formulas import adp_gram, synthetic, weighted_titsias_affine
from tolerances import (
    EPS,
    assert_within,
    contraction_tolerance,
    gamma,
    kernel_rtol,
    sparse_affine_tolerance,
)

from afvsgp_gym.gp import AFVSGP, VSGP, ADPKernel


def _kernel(b=3, m=2):
    return ADPKernel(np.full((m + 1, b), 1.3), np.array([1.0, 0.6, 0.4][: m + 1]))


def _check_against_batch(gp, xi, u, z, phi, xs):
    p = gp.window
    w = phi ** np.arange(p - 1, -1, -1, dtype=float)
    k = gp.kernel_
    bref, sref = weighted_titsias_affine(k.lengthscales, k.variances, gp.noise_variance_,
                                         xi[-p:], u[-p:], z[-p:], w, gp.inducing_xi_,
                                         gp.inducing_u_, xs, jitter=gp.jitter_)
    bvec, sig = gp.predict_affine(xs)
    tol_b, tol_s = sparse_affine_tolerance(gp, xs, (xi[-p:], u[-p:], z[-p:], w))
    assert_within(bvec, bref, tol_b, "b")
    assert_within(sig, sref, tol_s, "Sigma")


def test_phi_one_no_overflow_fixed_set_equals_vsgp():
    rng = np.random.default_rng(0)
    xi, u, z, _ = synthetic(rng, 400)
    ind = (xi[:12], u[:12])
    kw = dict(inducing=ind)
    a = AFVSGP(_kernel(), 0.02, num_inducing=12, window=400, forgetting=1.0,
               adapt_inducing=False, **kw).fit(xi[:50], u[:50], z[:50], False)
    v = VSGP(_kernel(), 0.02, **kw).fit(xi[:50], u[:50], z[:50], False)
    assert a.jitter_ == v.jitter_
    for i in range(50, 400):
        a.update(xi[i], u[i], z[i])
        v.update(xi[i], u[i], z[i])
    xs = rng.normal(size=(6, 3))
    # AFVSGP accumulated S and r over 350 rank-one updates (rebuilt every `window`), VSGP
    # whitens its kernel rows: the data-accumulation bound applies
    tols = sparse_affine_tolerance(a, xs, (xi, u, z, np.ones(400)))
    for got, ref, tol in zip(a.predict_affine(xs), v.predict_affine(xs), tols, strict=True):
        assert_within(got, ref, tol)
    kxo = np.abs(v.kernel_(xi, u, *ind))
    assert_within(a.S_, v.S_, 2 * gamma(400) * kxo.T @ kxo, "S")


@pytest.mark.parametrize("phi", [0.95, 1.0])
@pytest.mark.parametrize("adapt", [False, True])
def test_forgetting_window_equals_batch_weighted_posterior(adapt, phi):
    """>= 10 P streamed updates (window overflowing), with and without add/remove events."""
    rng = np.random.default_rng(1)
    p = 60
    n = p + 10 * p + 7
    xi, u, z, _ = synthetic(rng, n, noise_std=0.05)
    gp = AFVSGP(_kernel(), 0.0025, num_inducing=8, window=p, forgetting=phi,
                adapt_inducing=adapt, add_threshold=0.05, swap_margin=0.0)
    gp.fit(xi[:p], u[:p], z[:p], learn_hyperparameters=False)
    xs = rng.normal(size=(5, 3))
    added = []
    for i in range(p, n):
        gp.update(xi[i], u[i], z[i])
        added.append(gp.n_added_)
        if i % (3 * p) == 0:
            _check_against_batch(gp, xi[: i + 1], u[: i + 1], z[: i + 1], phi, xs)
    _check_against_batch(gp, xi, u, z, phi, xs)
    if adapt:
        assert gp.n_added_ > 0 and gp.n_removed_ > 0
        assert len(gp.inducing_xi_) == 8
        # events happened late in the stream too, between the checks
        assert added[-1] > added[len(added) // 2]
    else:
        assert gp.n_added_ == 0


def test_inducing_bookkeeping_matches_refactorisation():
    """chol(K_oo) after add/remove events equals the Cholesky of K_oo built from scratch."""
    rng = np.random.default_rng(2)
    xi, u, z, _ = synthetic(rng, 500, noise_std=0.05)
    gp = AFVSGP(_kernel(), 0.0025, num_inducing=6, window=50, forgetting=0.97,
                add_threshold=0.05, swap_margin=0.0).fit(xi[:50], u[:50], z[:50], False)
    for i in range(50, 500):
        gp.update(xi[i], u[i], z[i])
    assert gp.n_removed_ > 5
    k = gp.kernel_
    koo = adp_gram(k.lengthscales, k.variances, gp.inducing_xi_, gp.inducing_u_,
                   gp.inducing_xi_, gp.inducing_u_) + gp.jitter_ * np.eye(6)
    # each append / rank-one deletion is backward stable (gamma(M + 1) |L| |L'|, Higham
    # Thm. 10.3); errors add over the updates; the independent gram differs by kernel rounding
    low = gp._l_oo
    n_upd = gp.n_added_ + gp.n_removed_ + 1
    back = (n_upd * gamma(7) + kernel_rtol(k, gp.inducing_xi_)) * np.abs(low) @ np.abs(low.T)
    assert_within(low @ low.T, koo, back, "L L'")
    # the factor itself: perturbation theory of the Cholesky factor, |dL| <~ cond(K) |dK| |L|/|K|
    ref = np.linalg.cholesky(koo)
    rel = np.linalg.cond(koo) * np.max(back) / np.linalg.norm(koo, 2)
    assert_within(low, ref, 2 * rel * np.max(np.abs(ref)) + gamma(7) * np.abs(ref), "L")
    # no duplicates in the inducing set
    pairs = np.hstack([gp.inducing_xi_, gp.inducing_u_])
    assert len(np.unique(pairs.round(12), axis=0)) == 6


def test_duplicate_samples_never_become_inducing_points():
    rng = np.random.default_rng(3)
    xi, u, z, _ = synthetic(rng, 40, noise_std=0.05)
    gp = AFVSGP(_kernel(), 0.0025, num_inducing=10, window=40, add_threshold=0.0,
                swap_margin=0.0).fit(xi[:5], u[:5], z[:5], False)
    for _ in range(20):
        gp.update(xi[0], u[0], z[0])  # xi[0] is already an inducing point
    assert len(gp.inducing_xi_) == 5 and gp.n_added_ == 0


def test_inducing_set_settles_on_stationary_stream():
    rng = np.random.default_rng(4)
    n = 3000
    xi, u, z, _ = synthetic(rng, n, b=2, m=1, noise_std=0.1)
    gp = AFVSGP(num_inducing=15, window=200, forgetting=0.99).fit(xi[:200], u[:200], z[:200])
    changes = []
    for i in range(200, n):
        gp.update(xi[i], u[i], z[i])
        changes.append(gp.n_added_)
    changes = np.asarray(changes)
    first, last = changes[999], changes[-1] - changes[-1000]
    assert last <= max(3, first // 4), (first, last)


def test_fit_increases_bound_and_recovers_noise():
    rng = np.random.default_rng(5)
    noise_std = 0.2
    xi, u, z, _ = synthetic(rng, 200, noise_std=noise_std)
    gp0 = AFVSGP(num_inducing=20, window=200, forgetting=0.995).fit(xi, u, z, False)
    gp = AFVSGP(num_inducing=20, window=200, forgetting=0.995).fit(xi, u, z)
    from afvsgp_gym.gp.bound import weighted_bound

    w = 0.995 ** np.arange(199, -1, -1, dtype=float)
    b0 = weighted_bound(gp0.kernel_, gp0.noise_variance_, xi, u, z, w, gp0.inducing_xi_,
                        gp0.inducing_u_, gp0.jitter_).total
    b1 = weighted_bound(gp.kernel_, gp.noise_variance_, xi, u, z, w, gp.inducing_xi_,
                        gp.inducing_u_, gp.jitter_).total
    assert b1 > b0 + gamma(200) * abs(b0)
    assert gp.bound_ > b0 + gamma(200) * abs(b0)
    assert 0.5 * noise_std**2 < gp.noise_variance_ < 1.5 * noise_std**2  # within +-50 %


def test_nonstationary_gain_switch_afvsgp_recovers_vsgp_does_not():
    """Input gain flips sign midway; AFVSGP's one-step-ahead MSE is back below 2 s2 within
    P samples, VSGP's stays high (paper Table I claim in miniature)."""
    rng = np.random.default_rng(6)
    p, noise_std = 200, 0.1
    n1, n2 = 600, 400
    xa, ua, za, _ = synthetic(rng, n1, b=2, m=1, noise_std=noise_std, gain=2.0)
    xb, ub, zb, _ = synthetic(rng, n2, b=2, m=1, noise_std=noise_std, gain=-2.0)
    xi, u, z = np.vstack([xa, xb]), np.vstack([ua, ub]), np.concatenate([za, zb])
    af = AFVSGP(num_inducing=20, window=p, forgetting=0.98).fit(xi[:p], u[:p], z[:p])
    vs = VSGP(num_inducing=20).fit(xi[:p], u[:p], z[:p])
    err_a, err_v = [], []
    for i in range(p, n1 + n2):
        ma = af.predict(xi[i:i + 1], u[i:i + 1])[0][0]
        mv = vs.predict(xi[i:i + 1], u[i:i + 1])[0][0]
        err_a.append((ma - z[i]) ** 2)
        err_v.append((mv - z[i]) ** 2)
        af.update(xi[i], u[i], z[i])
        vs.update(xi[i], u[i], z[i])
    err_a, err_v = np.asarray(err_a), np.asarray(err_v)
    s2 = noise_std**2
    before = slice(n1 - p - 100, n1 - p)
    assert err_a[before].mean() < 2 * s2
    k = n1 - p  # index of the switch in the error arrays
    after = slice(k + p - 50, k + p)  # the last 50 of the first P samples after the switch
    assert err_a[after].mean() < 2 * s2, err_a[after].mean()
    assert err_v[after].mean() > 10 * s2, err_v[after].mean()


def test_window_samples_are_the_last_p_with_weights():
    rng = np.random.default_rng(7)
    xi, u, z, _ = synthetic(rng, 130)
    gp = AFVSGP(_kernel(), 0.01, window=50, forgetting=0.9).fit(xi[:20], u[:20], z[:20], False)
    for i in range(20, 130):
        gp.update(xi[i], u[i], z[i])
    wx, wu, wz, w = gp.window_samples()
    np.testing.assert_array_equal(wx, xi[-50:])
    np.testing.assert_array_equal(wu, u[-50:])
    np.testing.assert_array_equal(wz, z[-50:])
    np.testing.assert_allclose(w, 0.9 ** np.arange(49, -1, -1), rtol=2 * EPS)  # pow: <= 1 ulp


def test_predict_affine_agrees_with_predict_for_random_u():
    rng = np.random.default_rng(8)
    xi, u, z, _ = synthetic(rng, 300)
    gp = AFVSGP(num_inducing=15, window=100, forgetting=0.98).fit(xi[:100], u[:100], z[:100])
    for i in range(100, 300):
        gp.update(xi[i], u[i], z[i])
    xs, us = rng.normal(size=(8, 3)), rng.uniform(-2, 2, (8, 2))
    mean, var = gp.predict(xs, us)
    bvec, sig = gp.predict_affine(xs)
    ub = np.hstack([np.ones((8, 1)), us])
    tol_b, tol_s = sparse_affine_tolerance(gp, xs)
    tm, tv = contraction_tolerance(ub, tol_b, tol_s, bvec, sig)
    assert_within(np.einsum("ni,ni->n", bvec, ub), mean, tm, "mean")
    assert_within(np.einsum("ni,nij,nj->n", ub, sig, ub), var, tv, "variance")
    assert np.linalg.eigvalsh(sig).min() >= -3 * np.max(tol_s)
    for n in range(3):  # the one-point path (chol(K_oo + S/s2)) equals the batch path
        b1, s1 = gp.predict_affine(xs[n:n + 1])
        assert_within(b1[0], bvec[n], tol_b[n], "one-point b")
        assert_within(s1[0], sig[n], tol_s[n], "one-point Sigma")
