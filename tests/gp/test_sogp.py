"""Streaming sparse GP (Bui et al. 2017): batch equivalences, bound, affine form, bad input.
Tolerances: tests/gp/tolerances.py (first-order rounding bounds)."""

import warnings

import numpy as np
import pytest
from tolerances import (
    assert_within,
    central_difference,
    contraction_tolerance,
    gamma,
    kernel_rtol,
    sparse_affine_tolerance,
)

from afvsgp_gym.gp._linalg import DEFAULT_JITTER, ubar
from afvsgp_gym.gp.kernels import ADPKernel
from afvsgp_gym.gp.sogp import SOGP, _online_bound_and_grad

B, M_ACT = 3, 2


def _truth(xi, u):
    return np.sin(xi[:, 0]) + u[:, 0] * np.cos(xi[:, 1]) - 0.5 * u[:, 1] * xi[:, 2]


def _data(rng, n, noise=0.1):
    xi = rng.normal(size=(n, B))
    u = rng.uniform(-1, 1, size=(n, M_ACT))
    return xi, u, _truth(xi, u) + noise * rng.normal(size=n)


def _kernel(rng):
    return ADPKernel(rng.uniform(0.8, 2.0, (M_ACT + 1, B)), rng.uniform(0.3, 1.5, M_ACT + 1))


def _titsias(kern, s2, xi, u, z, xi_o, u_o, xs, us, jitter=DEFAULT_JITTER):
    """Batch Titsias 2009 posterior and bound (dense N x N, written out independently)."""
    kzz = kern(xi_o, u_o)
    kzz = kzz + jitter * np.mean(np.diag(kzz)) * np.eye(len(kzz))
    kzf = kern(xi_o, u_o, xi, u)
    sig = kzz + kzf @ kzf.T / s2
    ksz = kern(xs, us, xi_o, u_o)
    mean = ksz @ np.linalg.solve(sig, kzf @ z) / s2
    var = (kern.diag(xs, us) - np.sum(ksz * np.linalg.solve(kzz, ksz.T).T, axis=1)
           + np.sum(ksz * np.linalg.solve(sig, ksz.T).T, axis=1))
    q_mean = kzz @ np.linalg.solve(sig, kzf @ z) / s2
    q_cov = kzz @ np.linalg.solve(sig, kzz)
    qff = kzf.T @ np.linalg.solve(kzz, kzf)
    cov = qff + s2 * np.eye(len(z))
    _, logdet = np.linalg.slogdet(cov)
    quad = z @ np.linalg.solve(cov, z)
    bound = (-0.5 * len(z) * np.log(2 * np.pi) - 0.5 * logdet - 0.5 * quad
             - 0.5 * (np.sum(kern.diag(xi, u)) - np.trace(qff)) / s2)
    return mean, var, q_mean, q_cov, bound


def _bound_tol(kern, s2, xi, u, z, xi_o, u_o, jitter=DEFAULT_JITTER):
    """Rounding of the dense bound above (Q through K_zz: gamma(M) cond(K_zz); the Gaussian
    through C = Q + s2 I: gamma(N) cond(C)) plus the learner's (the N-term sums)."""
    kzz = kern(xi_o, u_o)
    kzz = kzz + jitter * np.mean(np.diag(kzz)) * np.eye(len(kzz))
    kzf = kern(xi_o, u_o, xi, u)
    mag_q = np.abs(kzf.T) @ np.abs(np.linalg.inv(kzz)) @ np.abs(kzf)
    err_q = gamma(len(kzz)) * np.linalg.cond(kzz) * mag_q
    cov = kzf.T @ np.linalg.solve(kzz, kzf) + s2 * np.eye(len(z))
    c = np.linalg.cond(cov)
    ref_err = (np.trace(err_q) / (2 * s2) + c * np.sum(np.abs(np.linalg.solve(cov, err_q)))
               + gamma(len(z)) * c * (abs(z @ np.linalg.solve(cov, z)) + len(z)))
    big = (z @ z + np.sum(kern.diag(xi, u))) / s2
    return ref_err + (4 * gamma(len(z)) + kernel_rtol(kern, xi, xi_o)) * big


def _stream(model, xi, u, z):
    for i in range(len(z)):
        model.update(xi[i], u[i], z[i])
    return model


def test_single_batch_from_prior_equals_titsias():
    rng = np.random.default_rng(0)
    kern, s2 = _kernel(rng), 0.05
    xi, u, z = _data(rng, 40)
    model = _stream(SOGP(kern, s2, num_inducing=12, batch_size=40), xi, u, z)
    assert model.n_seen_ == 40 and model.n_buffered == 0
    assert model.inducing_xi_.shape == (12, B)
    xs, us = rng.normal(size=(25, B)), rng.uniform(-1, 1, (25, M_ACT))
    mean, var, q_mean, q_cov, bound = _titsias(kern, s2, xi, u, z, model.inducing_xi_,
                                               model.inducing_u_, xs, us)
    got_mean, got_var = model.predict(xs, us)
    data = (xi, u, z, np.ones(40))
    tol_b, tol_s = sparse_affine_tolerance(model, xs, data)
    b, sig = model.predict_affine(xs)
    tm, tv = contraction_tolerance(np.hstack([np.ones((25, 1)), us]), tol_b, tol_s, b, sig)
    assert_within(got_mean, mean, tm, "mean")
    assert_within(got_var, var, tv, "variance")
    koo = kern(model.inducing_xi_, model.inducing_u_) + model.jitter_ * np.eye(12)
    tq_m, tq_c = sparse_affine_tolerance(model, None, data, rows=koo)
    assert_within(model.q_mean_, q_mean, tq_m, "q mean")
    assert_within(model.q_cov_, q_cov, tq_c, "q cov")
    assert_within(model.bound_, bound, _bound_tol(kern, s2, xi, u, z, model.inducing_xi_,
                                                  model.inducing_u_), "bound")


@pytest.mark.parametrize("batch_size", [1, 7])
def test_streaming_same_inducing_equals_batch(batch_size):
    """Bui et al.'s key property: b = a, fixed hyperparameters -> batch posterior."""
    rng = np.random.default_rng(1)
    kern, s2 = _kernel(rng), 0.02
    xi, u, z = _data(rng, 120)
    xi_o, u_o = rng.normal(size=(15, B)), rng.uniform(-1, 1, (15, M_ACT))
    model = SOGP(kern, s2, num_inducing=15, batch_size=batch_size, inducing=(xi_o, u_o),
                 adapt_inducing=False)
    model.fit(xi[:30], u[:30], z[:30], learn_hyperparameters=False)
    _stream(model, xi[30:], u[30:], z[30:]).flush()
    assert model.n_seen_ == 120
    np.testing.assert_array_equal(model.inducing_xi_, xi_o)
    xs, us = rng.normal(size=(30, B)), rng.uniform(-1, 1, (30, M_ACT))
    mean, var, q_mean, q_cov, bound = _titsias(kern, s2, xi, u, z, xi_o, u_o, xs, us)
    got_mean, got_var = model.predict(xs, us)
    # the stream accumulated Phit and rt over 90 steps: the data-accumulation bound, summed
    # over the steps' rounding (one gamma(M) per step on top of gamma(N + M))
    data = (xi, u, z, np.ones(120))
    steps = model.n_steps_
    tol_b, tol_s = (t * (1 + steps * gamma(15) / gamma(135))
                    for t in sparse_affine_tolerance(model, xs, data))
    b, sig = model.predict_affine(xs)
    tm, tv = contraction_tolerance(np.hstack([np.ones((30, 1)), us]), tol_b, tol_s, b, sig)
    assert_within(got_mean, mean, tm, "mean")
    assert_within(got_var, var, tv, "variance")
    koo = kern(xi_o, u_o) + model.jitter_ * np.eye(15)
    _, tq_c = sparse_affine_tolerance(model, None, data, rows=koo)
    assert_within(model.q_cov_, q_cov, tq_c * (1 + steps * gamma(15) / gamma(135)), "q cov")
    # the per-step online bounds add up to the batch bound (checks Bui's Delta_a terms); the
    # steps' sums have at most M + batch_size <= N terms each, over the same data in total
    assert_within(model.bound_, bound, _bound_tol(kern, s2, xi, u, z, xi_o, u_o), "bound")


def test_general_step_reduces_to_same_set_step():
    """The projected step (G = L_b^-1 K_ba L'^-T) with b = a matches the additive shortcut."""
    rng = np.random.default_rng(2)
    kern, s2 = _kernel(rng), 0.05
    xi, u, z = _data(rng, 60)
    model = SOGP(kern, s2, num_inducing=10).fit(xi[:40], u[:40], z[:40],
                                                learn_hyperparameters=False)
    st = model._state
    xi_p, u_p = np.vstack([st.xi, xi[40:]]), np.vstack([st.u, u[40:]])
    kpp = kern._gram(xi_p, ubar(u_p))
    step, eps = model._build_step(kern, s2, st, kpp, np.arange(st.size), st.size, z[40:])
    assert eps == st.eps
    val_gen, post_gen, _ = step.bound()
    val_same, post_same = step.same_set()
    # the general step projects with G = L_b^-1 K_ba L'^-T, I up to the triangular solves'
    # error gamma(M) cond(L) each; Phit = G Phit G' + A A', rt = G rt + A y / s move by
    # twice that relative to |Phit|, |rt|; F through log|D| (D >= I) and |L_D^-1 rt|^2
    cond_l = np.linalg.cond(st.chol)
    d_g = 2 * gamma(st.size) * cond_l
    phi, rt = post_same[1], post_same[2]
    tol_phi = 2 * d_g * np.linalg.norm(st.phi, 2) + gamma(st.size + 20) * np.linalg.norm(phi, 2)
    tol_rt = d_g * np.linalg.norm(st.r) + gamma(st.size + 20) * np.linalg.norm(rt)
    assert_within(post_gen[1], phi, tol_phi, "Phit")
    assert_within(post_gen[2], rt, tol_rt, "rt")
    beta = np.linalg.solve(np.eye(st.size) + phi, rt)
    tol_f = (st.size + beta @ beta) * tol_phi + 2 * np.linalg.norm(beta) * tol_rt
    assert_within(val_gen, val_same, tol_f + gamma(60) * abs(val_same), "F")


@pytest.mark.parametrize("change_theta", [False, True])
def test_general_step_matches_dense_bui_formula(change_theta):
    """Projected step (b mixes old and new points) vs Bui et al.'s bound and q(b), dense."""
    rng = np.random.default_rng(12)
    kern, s2 = _kernel(rng), 0.05
    xi, u, z = _data(rng, 55)
    model = SOGP(kern, s2, num_inducing=8, jitter=0.0).fit(xi[:40], u[:40], z[:40],
                                                           learn_hyperparameters=False)
    st = model._state
    xa, ua, m_a, s_a = st.xi, st.u, model.q_mean_, model.q_cov_
    kern2 = kern.with_theta(kern.theta + (0.2 * rng.normal(size=kern.n_params)
                                          if change_theta else 0.0))
    xf, uf, y = xi[40:], u[40:], z[40:]
    idx = np.array([0, 2, 3, 5, 8, 11, 15, 18])  # 4 old, 4 new points
    xi_p, u_p = np.vstack([xa, xf]), np.vstack([ua, uf])
    step, _ = model._build_step(kern2, s2, st, kern2._gram(xi_p, ubar(u_p)), idx, 8, y)
    value, post, _ = step.bound()
    lb, _, r, ld = post
    d_inv = np.linalg.inv(ld @ ld.T)
    got_mean, got_cov = lb @ d_inv @ r, lb @ d_inv @ lb.T
    # dense reference: old posterior as pseudo-data yhat_a with noise D_a (Bui et al. 2017)
    xb, ub_ = xi_p[idx], u_p[idx]
    kaa_old = kern(xa, ua)
    d_a = np.linalg.inv(np.linalg.inv(s_a) - np.linalg.inv(kaa_old))
    yhat = np.concatenate([y, d_a @ np.linalg.solve(s_a, m_a)])
    kbb = kern2(xb, ub_)
    kbx = np.hstack([kern2(xb, ub_, xf, uf), kern2(xb, ub_, xa, ua)])
    noise = np.zeros((len(yhat), len(yhat)))
    noise[:len(y), :len(y)] = s2 * np.eye(len(y))
    noise[len(y):, len(y):] = d_a
    khat = kbx.T @ np.linalg.solve(kbb, kbx)
    cov = khat + noise
    _, logdet = np.linalg.slogdet(cov)
    loglik = -0.5 * (len(yhat) * np.log(2 * np.pi) + logdet + yhat @ np.linalg.solve(cov, yhat))
    kaa = kern2(xa, ua)
    q_aa = khat[len(y):, len(y):]
    trace = (-0.5 * (np.sum(kern2.diag(xf, uf)) - np.trace(khat[:len(y), :len(y)])) / s2
             - 0.5 * np.trace(np.linalg.solve(d_a, kaa - q_aa)))
    ld = [np.linalg.slogdet(x)[1] for x in (kaa_old, s_a, d_a)]
    delta = (0.5 * (ld[0] - ld[1] + ld[2]) - 0.5 * m_a @ np.linalg.solve(s_a, m_a)
             + 0.5 * len(m_a) * np.log(2 * np.pi) + 0.5 * yhat[len(y):] @ np.linalg.solve(
                 d_a, yhat[len(y):]))
    # the dense reference inverts S_a, K'_aa, S_a^-1 - K'_aa^-1 (D_a), K_bb, cov and the
    # precision; each inverse or solve is exact up to gamma(n) cond(.) relative (Higham 14),
    # and the errors propagate to first order with the same condition numbers
    conds = [np.linalg.cond(x) for x in (s_a, kaa_old, d_a, kbb, cov)]
    kappa = gamma(len(yhat)) * sum(conds)
    terms = [loglik, trace, delta, 0.5 * logdet, 0.5 * len(yhat) * np.log(2 * np.pi)]
    assert_within(value, loglik + trace + delta, kappa * sum(abs(t) for t in terms), "F")
    kinv_kbx = np.linalg.solve(kbb, kbx)
    prec = np.linalg.inv(kbb) + kinv_kbx @ np.linalg.solve(noise, kinv_kbx.T)
    ref_cov = np.linalg.inv(prec)
    ref_mean = ref_cov @ kinv_kbx @ np.linalg.solve(noise, yhat)
    kappa_q = kappa + gamma(len(yhat)) * np.linalg.cond(prec)
    assert_within(got_mean, ref_mean, kappa_q * np.max(np.abs(ref_mean)), "q mean")
    assert_within(got_cov, ref_cov, kappa_q * np.max(np.abs(ref_cov)), "q cov")


def test_adaptive_streaming_tracks_batch_posterior():
    rng = np.random.default_rng(3)
    kern, s2 = _kernel(rng), 0.01
    xi, u, z = _data(rng, 300)
    model = SOGP(kern, s2, num_inducing=20, batch_size=10).fit(xi[:50], u[:50], z[:50],
                                                               learn_hyperparameters=False)
    _stream(model, xi[50:], u[50:], z[50:])
    assert model.inducing_xi_.shape[0] <= 20 and model.n_steps_ == 26
    xs, us = rng.normal(size=(200, B)), rng.uniform(-1, 1, (200, M_ACT))
    mean, var = model.predict(xs, us)
    ref, _, _, _, _ = _titsias(kern, s2, xi, u, z, model.inducing_xi_, model.inducing_u_, xs, us)
    err = np.mean((mean - _truth(xs, us)) ** 2)
    err_ref = np.mean((ref - _truth(xs, us)) ** 2)
    assert err < 2.0 * err_ref + 0.05 * np.var(_truth(xs, us))
    assert np.all(var >= 0) and np.all(np.isfinite(var))


def test_predict_affine_agrees_with_predict():
    rng = np.random.default_rng(4)
    xi, u, z = _data(rng, 80)
    model = SOGP(num_inducing=15, batch_size=5, fit_maxiter=30).fit(xi[:40], u[:40], z[:40])
    _stream(model, xi[40:], u[40:], z[40:])
    xs, us = rng.normal(size=(20, B)), rng.normal(size=(20, M_ACT))
    b, sigma = model.predict_affine(xs)
    assert b.shape == (20, M_ACT + 1) and sigma.shape == (20, M_ACT + 1, M_ACT + 1)
    np.testing.assert_array_equal(sigma, sigma.transpose(0, 2, 1))
    # lifted to PSD: eigvalsh is exact up to gamma(c) |Sigma| (Higham 15)
    c = M_ACT + 1
    top = np.max(np.abs(sigma), axis=(1, 2))
    assert np.all(np.linalg.eigvalsh(sigma).min(axis=1) >= -c * gamma(c) * top)
    ub = np.hstack([np.ones((20, 1)), us])
    mean, var = model.predict(xs, us)
    # the same posterior, two contraction orders; predict_affine's PSD lift adds <= |lambda|
    tol_b, tol_s = sparse_affine_tolerance(model, xs, (xi, u, z, np.ones(80)))
    tm, tv = contraction_tolerance(ub, tol_b, tol_s + 2e-14 * top[:, None, None], b, sigma)
    assert_within(np.einsum("ni,ni->n", b, ub), mean, tm, "mean")
    assert_within(np.einsum("ni,nij,nj->n", ub, sigma, ub), var, tv, "variance")


def test_fit_increases_bound_and_recovers_noise():
    rng = np.random.default_rng(5)
    xi, u, z = _data(rng, 200, noise=0.2)
    fixed = SOGP(num_inducing=20).fit(xi, u, z, learn_hyperparameters=False)
    learned = SOGP(num_inducing=20).fit(xi, u, z)
    assert learned.bound_ > fixed.bound_
    assert 0.5 * 0.04 < learned.noise_variance_ < 1.5 * 0.04


def test_online_bound_gradient_matches_finite_differences():
    rng = np.random.default_rng(6)
    kern, s2 = _kernel(rng), 0.05
    xi, u, z = _data(rng, 50)
    model = SOGP(kern, s2, num_inducing=8).fit(xi[:40], u[:40], z[:40],
                                               learn_hyperparameters=False)
    st = model._state
    xi_p, u_p = np.vstack([st.xi, xi[40:]]), np.vstack([st.u, u[40:]])
    ub_p = ubar(u_p)
    idx = np.array([0, 2, 3, 5, 6, 8, 11, 14])  # old and new points mixed: G is a projection
    f = np.arange(st.size, len(xi_p))
    work = kern.clone()
    p0 = np.concatenate([kern.theta + 0.1 * rng.normal(size=kern.n_params), [np.log(0.08)]])

    def value(p):
        work.theta = p[:-1]
        return _online_bound_and_grad(work, np.exp(p[-1]), st, xi_p, ub_p, idx, f, st.size,
                                      z[40:], 1e-6)

    val, grad = value(p0)

    def fun(p):  # value and the magnitude of its terms (data fit and trace, which cancel)
        v = value(p)[0]
        return v, abs(v) + (z[40:] @ z[40:] + 50.0 * np.max(kern.variances) * 4) / np.exp(p[-1])

    fd, err = central_difference(fun, p0, 1e-4)
    assert_within(grad, fd, err, "gradient")


def test_optimise_online_raises_the_step_bound():
    rng = np.random.default_rng(7)
    xi, u, z = _data(rng, 60)
    kern = _kernel(rng)
    base = SOGP(kern, 0.3, num_inducing=10, batch_size=20)
    opt = SOGP(kern, 0.3, num_inducing=10, batch_size=20, optimise_online=True,
               online_maxiter=10)
    for model in (base, opt):
        model.fit(xi[:40], u[:40], z[:40], learn_hyperparameters=False)
        _stream(model, xi[40:], u[40:], z[40:])
    assert opt.bound_ > base.bound_
    assert not np.array_equal(opt.kernel_.theta, kern.theta)
    np.testing.assert_array_equal(base.kernel_.theta, kern.theta)


def test_update_before_fit_fits_first_batch():
    rng = np.random.default_rng(8)
    xi, u, z = _data(rng, 30)
    model = SOGP(num_inducing=10, batch_size=15, fit_maxiter=10)
    _stream(model, xi[:14], u[:14], z[:14])
    with pytest.raises(RuntimeError, match="not fitted"):
        model.predict(xi[:2], u[:2])
    _stream(model, xi[14:], u[14:], z[14:])
    assert model.n_seen_ == 30 and model.n_steps_ == 2
    assert np.all(np.isfinite(model.predict(xi, u)[0]))


@pytest.mark.parametrize(("args", "name"), [
    ((np.zeros(B + 1), np.zeros(M_ACT), 0.0), "xi"),
    ((np.full(B, np.nan), np.zeros(M_ACT), 0.0), "xi"),
    ((np.zeros(B), np.zeros((1, M_ACT)), 0.0), "u"),
    ((np.zeros(B), np.array([0.0, np.inf]), 0.0), "u"),
    ((np.zeros(B), np.zeros(M_ACT), np.nan), "z"),
    ((np.zeros(B), np.zeros(M_ACT), np.zeros(2)), "z"),
])
def test_bad_update_raises_and_leaves_state(args, name):
    rng = np.random.default_rng(9)
    xi, u, z = _data(rng, 40)
    model = SOGP(num_inducing=10, batch_size=3, fit_maxiter=10).fit(xi, u, z)
    model.update(xi[0], u[0], z[0])
    xs, us = rng.normal(size=(5, B)), rng.normal(size=(5, M_ACT))
    before = model.predict(xs, us), model.predict_affine(xs), model.n_buffered
    with pytest.raises(ValueError, match=name):
        model.update(*args)
    after = model.predict(xs, us), model.predict_affine(xs), model.n_buffered
    for x, y in zip(before[:2], after[:2], strict=True):
        np.testing.assert_array_equal(x[0], y[0])
        np.testing.assert_array_equal(x[1], y[1])
    assert before[2] == after[2] == 1


def test_bad_fit_raises_and_leaves_state():
    rng = np.random.default_rng(10)
    xi, u, z = _data(rng, 30)
    model = SOGP(num_inducing=8, fit_maxiter=10).fit(xi, u, z)
    before = model.predict(xi, u)
    bad_z = z.copy()
    bad_z[3] = np.nan
    with pytest.raises(ValueError, match="z"):
        model.fit(xi, u, bad_z)
    with pytest.raises(ValueError, match="u"):
        model.fit(xi, u[:-1], z)
    with pytest.raises(ValueError, match="xi"):
        model.predict(xi[:, :2], u)
    after = model.predict(xi, u)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])


def test_near_duplicate_inputs_never_nan():
    rng = np.random.default_rng(11)
    xi0, u0 = rng.normal(size=(1, B)), rng.uniform(-1, 1, (1, M_ACT))
    xi = np.repeat(xi0, 40, axis=0) + 1e-12 * rng.normal(size=(40, B))
    u = np.repeat(u0, 40, axis=0)
    z = 0.3 + 0.01 * rng.normal(size=40)
    model = SOGP(num_inducing=10, batch_size=5, fit_maxiter=20).fit(xi[:20], u[:20], z[:20])
    _stream(model, xi[20:], u[20:], z[20:])
    assert model.inducing_xi_.shape[0] == 1  # near-duplicates never become inducing points
    mean, var = model.predict(xi[:5], u[:5])
    b, sigma = model.predict_affine(xi[:5])
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)
    assert np.all(np.isfinite(b)) and np.all(np.isfinite(sigma))
    # a fixed inducing set with exact duplicates and no jitter: Cholesky retries and warns
    kern = _kernel(rng)
    with pytest.warns(RuntimeWarning, match="jitter"):
        dup = SOGP(kern, 0.01, num_inducing=3, batch_size=5, inducing=(xi[:3], u[:3]),
                   adapt_inducing=False, jitter=0.0)
        dup.fit(xi[:20], u[:20], z[:20], learn_hyperparameters=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        _stream(dup, xi[20:], u[20:], z[20:])
    mean, var = dup.predict(xi[:5], u[:5])
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
    assert np.all(np.isfinite(dup.predict_affine(xi[:5])[1]))


def test_constructor_stores_parameters_only():
    kern = ADPKernel(np.ones((3, 2)), np.ones(3))
    model = SOGP(kern, 0.1, num_inducing=5, batch_size=2)
    assert model.kernel is kern and model.num_inducing == 5 and model.batch_size == 2
    assert not hasattr(model, "kernel_")
    with pytest.raises(ValueError, match="batch_size"):
        SOGP(batch_size=0).fit(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3))
