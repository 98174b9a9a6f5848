"""Sparse-GP numerics where the matrices are ill-conditioned (issue 10): the collapsed bound,
its gradient and the predictions against 40-digit references on the same float64 inputs
(``mp_reference``), the bound against the textbook N x N formula, and the fit.

Tolerances (``EPS`` = float64 machine epsilon, ``gamma(n) = n u / (1 - n u)``, ``u = EPS/2``):

- bound: ``4 gamma(N) (sum lambda z^2 + sum lambda k_tt) / s2``, the rounding of the N-term sums
  of the fit and trace terms, the two large terms that cancel, plus ``gamma(b + m + 4) (1 +
  max exponent)`` (the relative rounding of a float64 kernel entry) times the bound's
  sensitivity to relative perturbations of the kernel entries (``MpProblem.bound_sensitivity``,
  its condition number w.r.t. its inputs). The whitened form adds no factor of
  ``cond(K_oo + S/s2)`` (``D = I + A A' >= I``), which is what these points check;
- gradient: ``4 gamma(N) max_j sum |terms_j|``, where ``sum |terms_j|`` is the sum of the absolute
  values of the terms of ``dF/dtheta_j`` (``MpProblem.grad_analytic(magnitude=True)``);
- predictions: ``gamma(N + M)`` times the first-order sensitivity of eq. 20 to relative
  perturbations of ``K_oo + S/s2`` and ``r`` (``MpProblem.affine_rounding_bound``), plus
  ``gamma(M)`` times the prior variances for the cancellation in ``Sigma``.

The issue's acceptance thresholds (bound 1e-6, gradient 1e-4 relative) are checked as well.
"""

import numpy as np
import pytest
from mp_reference import MpProblem

from afvsgp_gym.gp import AFVSGP, SOGP, VSGP, ADPKernel, afvsgp_bank
from afvsgp_gym.gp._linalg import DEFAULT_JITTER, jitter_for, ubar
from afvsgp_gym.gp.bound import weighted_bound, weighted_bound_and_grad
from afvsgp_gym.gp.hyper import DEFAULT_PRIOR, noise_box, theta_box

EPS = np.finfo(np.float64).eps


def gamma(n: int) -> float:
    u = EPS / 2
    return n * u / (1 - n * u)


def _reproducer_data():
    """Issue 10's reproducer: N = 300, b = 3, m = 1, noise std 0.1."""
    rng = np.random.default_rng(1)
    n = 300
    xi = rng.uniform(-2, 2, (n, 3))
    u = rng.uniform(-1.5, 1.5, (n, 1))
    z = (np.sin(xi[:, 0]) + 0.5 * np.cos(1.5 * xi[:, 1]) + 0.075 * xi[:, 2] ** 2
         + (1 + 0.5 * np.sin(xi[:, 2]) + 0.3 * xi[:, 0]) * u[:, 0]
         + 0.1 * rng.standard_normal(n))
    return xi, u, z


#: ``concat(theta, [log s2])`` that VSGP.fit learned on the reproducer before issue 10 was fixed
#: (rounded): two lengthscales at the e^8 box edge, component variances 1 and 63.
REPRO_PARAMS = np.array([0.79, 0.55, 8.71, 3.74, 8.65, 3.86, 0.05, 4.14, -3.6])


@pytest.fixture(scope="module")
def repro():
    xi, u, z = _reproducer_data()
    v0 = VSGP(num_inducing=20).fit(xi, u, z, learn_hyperparameters=False)
    xo, uo = v0.inducing_xi_, v0.inducing_u_
    w = np.ones(len(z))
    kernel = ADPKernel(np.ones((2, 3)), np.ones(2)).with_theta(REPRO_PARAMS[:-1])
    jitter = jitter_for(kernel(xo, uo), DEFAULT_JITTER)
    return dict(xi=xi, u=u, z=z, w=w, xo=xo, uo=uo, kernel=kernel, jitter=jitter,
                s2=float(np.exp(REPRO_PARAMS[-1])), params=REPRO_PARAMS,
                mp=MpProblem(xi, u, z, w, xo, uo))


def _bound_tol(kernel, s2, xi, u, z, w, prob=None, params=None, jitter=0.0):
    """Rounding of the N-term sums; with ``prob``, plus the inherited kernel rounding."""
    tol = 4 * gamma(len(z)) * (w @ (z * z) + w @ kernel.diag(xi, u)) / s2
    if prob is not None:
        xo = np.array([[float(v) for v in row] for row in prob.xo])
        expo = np.max(np.sum(((xi[:, None] - xo[None]) / np.min(kernel.lengthscales)) ** 2, 2))
        b, m = xi.shape[1], u.shape[1]
        tol += gamma(b + m + 4) * (1 + 0.5 * expo) * prob.bound_sensitivity(params, jitter)
    return tol


def test_reproducer_point_is_ill_conditioned(repro):
    p = repro["params"]
    cond_koo, cond_sig = repro["mp"].condition(p[:-1], p[-1], repro["jitter"])
    assert cond_sig >= 1e10, cond_sig
    assert cond_koo >= 1e6, cond_koo


def test_bound_and_gradient_at_reproducer_match_high_precision(repro):
    r, p = repro, repro["params"]
    args = (r["xi"], r["u"], r["z"], r["w"], r["xo"], r["uo"])
    val, grad = weighted_bound_and_grad(p.copy(), r["kernel"].clone(), *args, r["jitter"])
    ref = float(r["mp"].bound(p[:-1], p[-1], r["jitter"]))
    tol = _bound_tol(r["kernel"], r["s2"], r["xi"], r["u"], r["z"], r["w"], r["mp"], p,
                     r["jitter"])
    assert abs(val - ref) <= tol, (val, ref, tol)
    assert abs(val - ref) <= 1e-6 * abs(ref)  # issue 10's acceptance
    ref_grad = r["mp"].grad_analytic(p, r["jitter"])
    mag = r["mp"].grad_analytic(p, r["jitter"], magnitude=True)
    err = np.max(np.abs(grad - ref_grad))
    assert err <= 4 * gamma(len(r["z"])) * mag.max(), (err, mag.max())
    assert err <= 1e-4 * np.max(np.abs(ref_grad))  # issue 10's acceptance
    # the named terms add up to the same value
    terms = weighted_bound(r["kernel"], r["s2"], *args, r["jitter"])
    assert abs(terms.total - val) <= tol


def test_reference_gradient_is_the_high_precision_finite_difference():
    """The analytic mp reference (textbook adjoints) against 40-digit central differences
    on a small problem (truncation ~1e-30, far below the float64 comparisons it serves)."""
    xi, u, z, w, xo, uo, kern, s2, jitter = _constructed("near_duplicates")
    prob = MpProblem(xi, u, z, w, xo, uo)
    params = np.r_[kern.theta, np.log(s2)]
    for relative in (False, True):
        ana = prob.grad_analytic(params, jitter, relative)
        fd = prob.grad(params, jitter, relative)
        # both are ~1e-25 from the exact gradient in mp: equal to one ulp once rounded
        np.testing.assert_allclose(ana, fd, rtol=EPS, atol=EPS * np.abs(fd).max())


def _constructed(kind: str):
    """Small weighted problems with cond(K_oo + S/s2) >= 1e10 built on purpose."""
    rng = np.random.default_rng(7)
    n, b = 40, 2
    xi = rng.normal(size=(n, b))
    u = rng.uniform(-1, 1, (n, 1))
    z = np.sin(xi[:, 0]) + u[:, 0] * (1 + 0.3 * xi[:, 1]) + 1e-3 * rng.normal(size=n)
    w = 0.97 ** np.arange(n)[::-1]
    if kind == "near_duplicates":  # pairs of inducing points 1e-4 lengthscales apart
        kern = ADPKernel(np.array([[1.0, 1.5], [2.0, 1.0]]), np.array([1.0, 2.0]))
        xo = np.vstack([xi[:4], xi[:4] + 1e-4])
        uo = np.vstack([u[:4], u[:4]])
        return xi, u, z, w, xo, uo, kern, 1e-6, 1e-12
    # long lengthscales and large variances: K_oo numerically of low rank
    kern = ADPKernel(np.full((2, b), 300.0), np.array([1e3, 5e2]))
    return xi, u, z, w, xi[:8], u[:8], kern, 1e-4, 1e-8 * np.mean(kern.diag(xi[:8], u[:8]))


@pytest.mark.parametrize("kind", ["near_duplicates", "long_lengthscales"])
def test_constructed_ill_conditioned_points(kind):
    """Bound against the M x M reference and the textbook N x N Titsias formula (both in 40
    digits), gradient against the reference, at points built to be ill-conditioned."""
    xi, u, z, w, xo, uo, kern, s2, jitter = _constructed(kind)
    prob = MpProblem(xi, u, z, w, xo, uo)
    params = np.r_[kern.theta, np.log(s2)]
    cond_koo, cond_sig = prob.condition(params[:-1], params[-1], jitter)
    assert cond_sig >= 1e10, cond_sig
    val, grad = weighted_bound_and_grad(params.copy(), kern.clone(), xi, u, z, w, xo, uo,
                                        jitter)
    ref = float(prob.bound(params[:-1], params[-1], jitter))
    dense = float(prob.bound_dense(params[:-1], params[-1], jitter))
    assert abs(ref - dense) <= 1e-25 * abs(dense)  # the two reference formulas agree
    tol = _bound_tol(kern, s2, xi, u, z, w, prob, params, jitter)
    assert abs(val - dense) <= tol, (val, dense, tol)
    ref_grad = prob.grad_analytic(params, jitter)
    mag = prob.grad_analytic(params, jitter, magnitude=True)
    assert np.max(np.abs(grad - ref_grad)) <= 4 * gamma(len(z)) * mag.max()


def _affine_tol(prob, params, jitter, xs, var):
    tol_b, tol_s = prob.affine_rounding_bound(params[:-1], params[-1], jitter, xs)
    g = gamma(prob.n + prob.m)
    scale = np.sqrt(np.outer(var, var))
    return g * tol_b, g * tol_s + 3 * gamma(prob.m) * scale


@pytest.mark.parametrize("backend", ["numpy", pytest.param("compiled", marks=pytest.mark.skipif(
    afvsgp_bank._core is None, reason="compiled core not built"))])
def test_predictions_at_reproducer_match_high_precision(repro, backend):
    """VSGP (whitened from its kernel rows), AFVSGP (from accumulated S, r: general and
    one-point paths, the latter by the bank's numpy method or its compiled core) and SOGP
    against the 40-digit posterior, within the rounding bound."""
    r, p = repro, repro["params"]
    xi, u, z, xo, uo = r["xi"], r["u"], r["z"], r["xo"], r["uo"]
    kern, s2 = r["kernel"], r["s2"]
    xs = np.random.default_rng(5).uniform(-2, 2, (3, 3))
    b_ref, s_ref = r["mp"].affine(p[:-1], p[-1], r["jitter"], xs)
    tol_b, tol_s = _affine_tol(r["mp"], p, r["jitter"], xs, kern.variances)
    learners = {
        "vsgp": VSGP(kern, s2, inducing=(xo, uo)),
        "afvsgp": AFVSGP(kern, s2, num_inducing=20, window=len(z), forgetting=1.0,
                         inducing=(xo, uo), adapt_inducing=False),
        "sogp": SOGP(kern, s2, num_inducing=20, inducing=(xo, uo), adapt_inducing=False),
    }
    for name, gp in learners.items():
        gp.fit(xi, u, z, learn_hyperparameters=False)
        assert gp.kernel_ is not kern
        if name == "afvsgp":
            gp._bank.backend = backend
        bvec, sig = gp.predict_affine(xs)
        assert np.all(np.abs(bvec - b_ref) <= tol_b), (name, np.abs(bvec - b_ref).max())
        assert np.all(np.abs(sig - s_ref) <= tol_s), (name, np.abs(sig - s_ref).max())
        for n in range(len(xs)):  # one-point paths (AFVSGP: its own factorisation)
            b1, s1 = gp.predict_affine(xs[n:n + 1])
            assert np.all(np.abs(b1[0] - b_ref[n]) <= tol_b[n]), name
            assert np.all(np.abs(s1[0] - s_ref[n]) <= tol_s[n]), name


def test_vsgp_predictions_from_kernel_rows_are_accurate_to_the_kernel_rounding(repro):
    """VSGP whitens its stored kernel rows (no S is formed), so at the reproducer its mean is
    as accurate as the float64 kernel values allow: relative perturbations of size
    ``gamma(b + m + 2)`` of the kernel entries (the exponent's rounding), through the
    first-order sensitivity of the mean, bound its error."""
    r, p = repro, repro["params"]
    kern, s2 = r["kernel"], r["s2"]
    gp = VSGP(kern, s2, inducing=(r["xo"], r["uo"])).fit(r["xi"], r["u"], r["z"], False)
    xs = np.random.default_rng(5).uniform(-2, 2, (3, 3))
    b_ref, _ = r["mp"].affine(p[:-1], p[-1], r["jitter"], xs)
    tol_b, _ = r["mp"].affine_rounding_bound(p[:-1], p[-1], r["jitter"], xs)
    # the same sensitivity, but to relative kernel-entry errors of gamma(b + m + 2) * |exponent|
    k_scale = gamma(3 + 1 + 2) * (1 + np.max(np.sum((r["xi"][:, None] - r["xo"][None]) ** 2, 2)
                                             / np.min(kern.lengthscales) ** 2))
    bvec, _ = gp.predict_affine(xs)
    assert np.all(np.abs(bvec - b_ref) <= k_scale * tol_b)


@pytest.mark.parametrize("fixed_set", [True, False])
def test_fit_ends_stationary_on_its_final_set_and_bound_is_reported_there(fixed_set):
    """After ``fit``, ``bound_`` is the bound at the fitted hyperparameters on the final inducing
    set, and the projected gradient of (bound + prior) there, computed accurately, is near
    zero: below 1e-6 of the sum of the bound's term magnitudes per unit log parameter, the
    scale at which L-BFGS-B's relative-reduction test (1e-12) stops."""
    xi, u, z = _reproducer_data()
    v0 = VSGP(num_inducing=20).fit(xi, u, z, learn_hyperparameters=False)
    kw = {"inducing": (v0.inducing_xi_, v0.inducing_u_)} if fixed_set else {}
    gp = VSGP(**kw).fit(xi, u, z)
    w = np.ones(len(z))
    ref = weighted_bound(gp.kernel_, gp.noise_variance_, xi, u, z, w, gp.inducing_xi_,
                         gp.inducing_u_, gp.jitter_)
    assert abs(gp.bound_ - ref.total) <= _bound_tol(gp.kernel_, gp.noise_variance_, xi, u, z, w)
    params = np.r_[gp.kernel_.theta, np.log(gp.noise_variance_)]
    _, grad = weighted_bound_and_grad(params, gp.kernel_.clone(), xi, u, z, w, gp.inducing_xi_,
                                      gp.inducing_u_, DEFAULT_JITTER, relative_jitter=True)
    center = v0.kernel_.theta  # the initial kernel: ADPKernel.from_data
    grad[:-1] += DEFAULT_PRIOR.log_density(params[:-1], center, 6)[1]
    box = np.array(theta_box(center) + [noise_box(z)])
    projected = np.clip(params + grad, box[:, 0], box[:, 1]) - params
    scale = sum(abs(t) for t in ref)
    assert np.max(np.abs(projected)) <= 1e-6 * scale, (np.abs(projected).max(), scale)


def test_prior_keeps_the_reproducer_fit_well_conditioned():
    """With the default prior the fitted K_oo + S/s2 is far better conditioned than at the
    pre-fix point (>= 1e10); without it the bound alone drifts back to >= 1e10."""
    xi, u, z = _reproducer_data()
    conds = {}
    for name, prior in (("default", DEFAULT_PRIOR), ("none", None)):
        gp = VSGP(prior=prior).fit(xi, u, z)
        koo = gp.kernel_(gp.inducing_xi_, gp.inducing_u_) + gp.jitter_ * np.eye(20)
        conds[name] = np.linalg.cond(koo + gp.S_ / gp.noise_variance_)
    assert conds["default"] < 1e9 < 1e10 <= conds["none"], conds


@pytest.mark.parametrize("name", ["vsgp", "afvsgp", "sogp"])
def test_bound_attribute_is_the_bound_on_the_final_inducing_set(name):
    xi, u, z = _reproducer_data()
    xi, u, z = xi[:150], u[:150], z[:150]
    gp = {"vsgp": VSGP(num_inducing=12, max_iter=60),
          "afvsgp": AFVSGP(num_inducing=12, window=150, forgetting=0.99, max_iter=60),
          "sogp": SOGP(num_inducing=12, fit_maxiter=60)}[name].fit(xi, u, z)
    w = (0.99 ** np.arange(149, -1, -1.0)) if name == "afvsgp" else np.ones(150)
    jitter = jitter_for(gp.kernel_._gram(gp.inducing_xi_, ubar(gp.inducing_u_)), DEFAULT_JITTER)
    ref = weighted_bound(gp.kernel_, gp.noise_variance_, xi, u, z, w, gp.inducing_xi_,
                         gp.inducing_u_, jitter).total
    assert abs(gp.bound_ - ref) <= _bound_tol(gp.kernel_, gp.noise_variance_, xi, u, z, w)
