"""AFVSGP per-step path: the one-point ``predict_affine`` and the update, checked against the
independent batch formula and against the many-point path; interleaving predictions with
updates (at the next update's point or elsewhere) never changes the state."""

import numpy as np
import pytest
from gp_batch_formulas import synthetic, weighted_titsias_affine
from tolerances import assert_within, sparse_affine_tolerance, warned_jitter

from afvsgp_gym.gp import AFVSGP, ADPKernel


def _kernel(b=3, m=2):
    return ADPKernel(np.full((m + 1, b), 1.3), np.array([1.0, 0.6, 0.4][: m + 1]))


def _learner(xi, u, z, p, **kw):
    opts = dict(num_inducing=8, window=p, forgetting=0.95, add_threshold=0.05,
                swap_margin=0.0)
    opts.update(kw)
    return AFVSGP(_kernel(), 0.0025, **opts).fit(xi[:p], u[:p], z[:p], False)


def _batch(gp, xi, u, z, xs):
    """Batch reference and the tolerance of the comparison (S accumulated from the data)."""
    p, phi = gp.window, gp.forgetting
    w = phi ** np.arange(p - 1, -1, -1, dtype=float)
    k = gp.kernel_
    ref = weighted_titsias_affine(k.lengthscales, k.variances, gp.noise_variance_,
                                  xi[-p:], u[-p:], z[-p:], w, gp.inducing_xi_,
                                  gp.inducing_u_, xs, jitter=gp.jitter_)
    return ref, sparse_affine_tolerance(gp, xs, (xi[-p:], u[-p:], z[-p:], w))


@pytest.mark.parametrize("at_next", [True, False])
def test_one_point_predictions_equal_batch_formula_through_inducing_events(at_next):
    """Stream with a prediction each step (at the next update's xi, or at another point);
    every one-point prediction at checkpoints equals the
    batch weighted Titsias posterior, also right after add/remove events."""
    rng = np.random.default_rng(11)
    p = 40
    n = p + 8 * p
    xi, u, z, _ = synthetic(rng, n, noise_std=0.05)
    gp = _learner(xi, u, z, p)
    other = rng.normal(size=(1, 3))
    checked_after_event = 0
    for i in range(p, n):
        before = gp.n_added_
        gp.update(xi[i], u[i], z[i])
        if i + 1 < n:
            bvec, sig = gp.predict_affine(xi[i + 1:i + 2] if at_next else other)
        if i % 23 == 0 or gp.n_added_ != before:
            xs = xi[i + 1:i + 2] if (at_next and i + 1 < n) else other
            b1, s1 = gp.predict_affine(xs)
            (bref, sref), (tol_b, tol_s) = _batch(gp, xi[: i + 1], u[: i + 1], z[: i + 1], xs)
            assert_within(b1, bref, tol_b, "b")
            assert_within(s1, sref, tol_s, "Sigma")
            np.testing.assert_array_equal(s1[0], s1[0].T)  # exactly symmetric
            checked_after_event += gp.n_added_ != before
    assert gp.n_added_ > 0 and gp.n_removed_ > 0 and checked_after_event > 0


def test_one_point_path_equals_general_path():
    rng = np.random.default_rng(12)
    p = 50
    xi, u, z, _ = synthetic(rng, 300)
    gp = _learner(xi, u, z, p)
    for i in range(p, 300):
        gp.update(xi[i], u[i], z[i])
    xs = rng.normal(size=(4, 3))
    ball, sall = gp.predict_affine(xs)  # N > 1: the general (whitened) path
    tol_b, tol_s = sparse_affine_tolerance(gp, xs)  # the same statistics, other algebra
    for n in range(4):
        for arg in (xs[n:n + 1], xs[n:n + 1].tolist()):  # fast path, validated path
            b1, s1 = gp.predict_affine(arg)
            assert b1.shape == (1, 3) and s1.shape == (1, 3, 3)
            assert_within(b1[0], ball[n], tol_b[n], "b")
            assert_within(s1[0], sall[n], tol_s[n], "Sigma")
    # results are fresh arrays: a later call does not change earlier results
    b1, s1 = gp.predict_affine(xs[:1])
    keep = b1.copy(), s1.copy()
    gp.predict_affine(xs[1:2])
    gp.update(xi[0], u[0], z[0])
    np.testing.assert_array_equal(b1, keep[0])
    np.testing.assert_array_equal(s1, keep[1])


def test_predicting_at_the_next_point_leaves_the_state_unchanged():
    """Predicting at each next xi or not at all gives identical learners: same statistics,
    inducing set and predictions."""
    rng = np.random.default_rng(13)
    p = 40
    xi, u, z, _ = synthetic(rng, 500, noise_std=0.05)
    a = _learner(xi, u, z, p)
    b = _learner(xi, u, z, p)
    for i in range(p, 500):
        a.predict_affine(xi[i:i + 1])
        a.update(xi[i], u[i], z[i])
        b.update(xi[i], u[i], z[i])
    assert a.n_added_ == b.n_added_ > 0
    np.testing.assert_array_equal(a.inducing_xi_, b.inducing_xi_)
    np.testing.assert_array_equal(a.S_, b.S_)
    np.testing.assert_array_equal(a.r_, b.r_)
    xs = rng.normal(size=(1, 3))
    for got, ref in zip(a.predict_affine(xs), b.predict_affine(xs), strict=True):
        np.testing.assert_array_equal(got, ref)


def test_update_at_a_point_other_than_the_prediction():
    """predict at x1, update at x0, update at x1 gives the learner that never predicted."""
    rng = np.random.default_rng(14)
    p = 30
    xi, u, z, _ = synthetic(rng, 200)
    a = _learner(xi, u, z, p)
    b = _learner(xi, u, z, p)
    for i in range(p, 198, 2):
        a.predict_affine(xi[i + 1:i + 2])
        a.update(xi[i], u[i], z[i])
        a.update(xi[i + 1], u[i + 1], z[i + 1])
        b.update(xi[i], u[i], z[i])
        b.update(xi[i + 1], u[i + 1], z[i + 1])
    np.testing.assert_array_equal(a.S_, b.S_)
    np.testing.assert_array_equal(a.r_, b.r_)
    for got, ref in zip(a.window_samples(), b.window_samples(), strict=True):
        np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("bad", ["u", "xi", "z"])
def test_rejected_update_after_prediction_leaves_state_and_row_intact(bad):
    rng = np.random.default_rng(15)
    p = 30
    xi, u, z, _ = synthetic(rng, 100)
    gp = _learner(xi, u, z, p)
    ref = _learner(xi, u, z, p)
    for i in range(p, 60):
        gp.update(xi[i], u[i], z[i])
        ref.update(xi[i], u[i], z[i])
    x = xi[60:61]
    before = gp.predict_affine(x)
    args = {"xi": (np.array([np.nan, 0.0, 0.0]), u[60], z[60]),
            "u": (xi[60], np.array([np.inf, 0.0]), z[60]),
            "z": (xi[60], u[60], np.nan)}[bad]
    with pytest.raises(ValueError, match=bad):
        gp.update(*args)
    after = gp.predict_affine(x)
    for got, exp in zip(after, before, strict=True):
        np.testing.assert_array_equal(got, exp)
    gp.update(xi[60], u[60], z[60])
    ref.update(xi[60], u[60], z[60])
    np.testing.assert_array_equal(gp.S_, ref.S_)
    for got, exp in zip(gp.predict_affine(x), ref.predict_affine(x), strict=True):
        np.testing.assert_array_equal(got, exp)


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning",
                            "ignore:invalid value:RuntimeWarning")
def test_one_point_prediction_far_away_and_huge_inputs_are_finite():
    rng = np.random.default_rng(16)
    xi, u, z, _ = synthetic(rng, 60)
    gp = _learner(xi, u, z, 30)
    for x in ([[1e3, -1e3, 0.0]], [[1e200, 0.0, 0.0]]):
        bvec, sig = gp.predict_affine(np.array(x))
        assert np.all(np.isfinite(bvec)) and np.all(np.isfinite(sig))
        # exp underflows to exactly 0 this far away: the prior, exactly
        np.testing.assert_array_equal(sig[0], np.diag(gp.kernel_.variances))
    with pytest.raises(ValueError, match="xi"):
        gp.predict_affine(np.array([[np.inf, 0.0, 0.0]]))


def test_singular_posterior_matrix_needs_no_retry():
    """Duplicate inducing points, no jitter and no data nearby: K_oo + S/s2 is singular, yet
    the whitened posterior (D = I + L^-1 S L^-T / s2 >= I) factors without a retry, and the
    one-point and many-point paths agree."""
    import warnings

    rng = np.random.default_rng(17)
    xi, u, z, _ = synthetic(rng, 40)
    ind = (np.vstack([xi[:3], xi[:3]]), np.vstack([u[:3], u[:3]]))
    gp = AFVSGP(_kernel(), 0.01, num_inducing=6, window=20, inducing=ind,
                adapt_inducing=False, jitter=0.0)
    with pytest.warns(RuntimeWarning, match="K_oo") as fit_record:  # K_oo itself needs jitter
        gp.fit(xi[:20] + 50.0, u[:20], z[:20], learn_hyperparameters=False)
    gp.update(xi[21] + 50.0, u[21], z[21])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        b1, s1 = gp.predict_affine(xi[:1])
        ball, sall = gp.predict_affine(xi[:2])
    assert np.all(np.isfinite(b1)) and np.all(np.isfinite(s1))
    assert np.all(gp.S_ == 0.0)  # the data are 50 lengthscales away: exp underflows
    tol_b, tol_s = sparse_affine_tolerance(gp, xi[:1], extra_jitter=warned_jitter(fit_record))
    assert_within(b1[0], ball[0], tol_b[0], "b")
    assert_within(s1[0], sall[0], tol_s[0], "Sigma")


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_copies_of_a_fitted_learner_stream_identically_and_independently(how):
    """The per-step buffers are views of a few arrays; a copy rebinds them (a copy that kept
    stale views would diverge at its first update)."""
    import copy
    import pickle

    rng = np.random.default_rng(18)
    p = 40
    xi, u, z, _ = synthetic(rng, 400, noise_std=0.05)
    gp = _learner(xi, u, z, p)
    for i in range(p, 100):
        gp.predict_affine(xi[i:i + 1])
        gp.update(xi[i], u[i], z[i])
    gp.predict_affine(xi[100:101])  # the copy also carries the reusable kernel row
    dup = copy.deepcopy(gp) if how == "deepcopy" else pickle.loads(pickle.dumps(gp))
    ref = _learner(xi, u, z, p)
    for i in range(p, 100):
        ref.update(xi[i], u[i], z[i])
    for i in range(100, 400):
        for learner in (dup, ref):
            learner.predict_affine(xi[i:i + 1])
            learner.update(xi[i], u[i], z[i])
    assert dup.n_added_ > gp.n_added_  # inducing events happened after the copy
    assert gp.n_seen_ == 100  # the original is untouched
    xs = rng.normal(size=(1, 3))
    for got, exp in zip(dup.predict_affine(xs), ref.predict_affine(xs), strict=True):
        np.testing.assert_array_equal(got, exp)
    for got, exp in zip(dup.window_samples(), ref.window_samples(), strict=True):
        np.testing.assert_array_equal(got, exp)
