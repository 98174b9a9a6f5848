"""AFVSGPBank: K learners in stacked arrays equal K independent AFVSGP learners and the batch
weighted Titsias posterior, through inducing-set changes; bad input changes nothing."""

import copy
import pickle

import numpy as np
import pytest
from gp_batch_formulas import synthetic, weighted_titsias_affine

from afvsgp_gym.gp import AFVSGP, ADPKernel
from afvsgp_gym.gp.afvsgp_bank import AFVSGPBank

K, P = 4, 40


def _streams(n):
    return [synthetic(np.random.default_rng(10 + k), n, noise_std=0.05) for k in range(K)]


def _learners(streams, u, n_fit=P, **kw):
    """One AFVSGP per stream with known hyperparameters, fitted on its first ``n_fit``
    samples."""
    opts = dict(num_inducing=8, window=P, forgetting=0.95, add_threshold=0.05, swap_margin=0.0)
    opts.update(kw)
    out = []
    for k, (xi, _, z, _) in enumerate(streams):
        ker = ADPKernel(np.full((3, 3), 1.0 + 0.2 * k), np.array([1.0, 0.6, 0.4]))
        out.append(AFVSGP(ker, 0.0025 * (k + 1), **opts).fit(xi[:n_fit], u[:n_fit], z[:n_fit],
                                                              False))
    return out


def _rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def _rows(streams, i):
    return (np.array([s[0][i] for s in streams]), np.array([s[2][i] for s in streams]))


def _assert_equals_batch_posterior(bank, streams, u, n, seed):
    """The bank's affine prediction at random points equals the weighted Titsias posterior of
    each learner's last P samples on its current inducing set (independent batch formula)."""
    xs = np.random.default_rng(seed).normal(size=(K, 3))
    b, s = bank.predict_affine(xs)
    w = 0.95 ** np.arange(P - 1, -1, -1, dtype=float)
    for k, (xi, _, z, _) in enumerate(streams):
        kern = bank.kernels[k]
        bref, sref = weighted_titsias_affine(
            kern.lengthscales, kern.variances, bank.noise_variance[k], xi[n - P : n],
            u[n - P : n], z[n - P : n], w, *bank.inducing(k), xs[k : k + 1],
            jitter=bank.jitter[k])
        assert _rel(b[k], bref[0]) < 1e-7 and _rel(s[k], sref[0]) < 1e-7


def test_bank_equals_independent_learners_through_inducing_events():
    n = P + 10 * P
    streams = _streams(n)
    u = streams[0][1]  # one action for every barrier, as in the filter
    learners = _learners(streams, u)
    bank = AFVSGPBank.from_learners(learners)
    rng = np.random.default_rng(3)
    worst = 0.0
    for i in range(P, n):
        xi, z = _rows(streams, i)
        for k in range(K):
            learners[k].update(xi[k], u[i], z[k])
        bank.update(xi, u[i], z)
        if i % 7 == 0:
            xs = rng.normal(size=(K, 3))
            b, s = bank.predict_affine(xs)
            for k in range(K):
                b1, s1 = learners[k].predict_affine(xs[k : k + 1])
                worst = max(worst, _rel(b[k], b1[0]), _rel(s[k], s1[0]))
    # the same arithmetic in another order: rounding-level differences (M = 8, cond(K_oo +
    # S/s2) < 1e8 here), far below any modelling difference
    assert worst < 1e-8
    np.testing.assert_array_equal(bank.n_added_, [lr.n_added_ for lr in learners])
    np.testing.assert_array_equal(bank.n_removed_, [lr.n_removed_ for lr in learners])
    assert bank.n_added_.min() > 50 and bank.n_removed_.min() > 50


def test_bank_equals_the_batch_weighted_posterior():
    """Against the independent batch formula over each learner's last P samples."""
    n = P + 6 * P
    streams = _streams(n)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u))
    for i in range(P, n):
        xi, z = _rows(streams, i)
        bank.update(xi, u[i], z)
    _assert_equals_batch_posterior(bank, streams, u, n, seed=5)


def test_window_returns_each_learners_last_samples_oldest_first():
    streams = _streams(P + P // 2 + 3)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u, n_fit=P // 2))
    for k in range(K):  # the fit's samples, not yet full
        xi, uu, z = bank.window_samples(k)
        np.testing.assert_array_equal(z, streams[k][2][: P // 2])
        np.testing.assert_array_equal(uu, u[: P // 2])
    n = len(u)
    for i in range(P // 2, n):  # the ring wraps: the last P samples
        bank.update(*_rows(streams, i)[:1], u[i], _rows(streams, i)[1])
    for k in range(K):
        xi, uu, z = bank.window_samples(k)
        np.testing.assert_array_equal(xi, streams[k][0][n - P : n])
        np.testing.assert_array_equal(uu, u[n - P : n])
        np.testing.assert_array_equal(z, streams[k][2][n - P : n])


def test_subset_prediction_equals_full_prediction():
    streams = _streams(2 * P)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u))
    xs = np.random.default_rng(1).normal(size=(K, 3))
    b, s = bank.predict_affine(xs)
    rows = np.array([3, 1])
    b2, s2 = bank.predict_affine(xs[rows], rows)
    np.testing.assert_allclose(b2, b[rows], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(s2, s[rows], rtol=1e-13, atol=1e-15)


def test_non_finite_rows_are_skipped_and_bad_input_changes_nothing():
    streams = _streams(3 * P)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u))
    xi, z = _rows(streams, P)
    z[1] = np.nan
    xi[2, 0] = np.inf
    before = copy.deepcopy(bank)
    ok = bank.update(xi, u[P], z)
    np.testing.assert_array_equal(ok, [True, False, False, True])
    np.testing.assert_array_equal(bank.n_seen_ - before.n_seen_, [1, 0, 0, 1])
    xs = np.random.default_rng(2).normal(size=(K, 3))
    for k in (1, 2):  # untouched learners: identical state and predictions
        for a, b in ((bank.statistics(k), before.statistics(k)),
                     (bank.predict_affine(xs[k:k + 1], [k]),
                      before.predict_affine(xs[k:k + 1], [k]))):
            for x, y in zip(a, b, strict=True):
                np.testing.assert_array_equal(x, y)
    snap = pickle.dumps(bank)
    for args, match in (((xi[:2], u[P], z[:2]), "xi"), ((xi, u[P][:1], z), "u"),
                        ((xi, np.array([np.nan, 0.0]), z), "u")):
        with pytest.raises(ValueError, match=match):
            bank.update(*args)
    assert pickle.dumps(bank) == snap


def test_learners_with_different_settings_are_refused():
    streams = _streams(2 * P)
    u = streams[0][1]
    a = _learners(streams[:1], u)
    b = _learners(streams[1:2], u, window=P // 2)
    with pytest.raises(ValueError, match="window"):
        AFVSGPBank.from_learners(a + b)
    with pytest.raises(ValueError, match="fitted AFVSGP"):
        AFVSGPBank.from_learners([AFVSGP()])


def test_at_most_one_inducing_change_per_step_keeps_the_posterior_exact():
    """With ``max_inducing_candidates=1`` at most one learner changes its inducing set in a step,
    and each learner still equals the batch weighted posterior on its own inducing set."""
    n = P + 6 * P
    streams = _streams(n)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), max_inducing_candidates=1)
    for i in range(P, n):
        before = bank.n_added_.copy()
        xi, z = _rows(streams, i)
        bank.update(xi, u[i], z)
        assert (bank.n_added_ - before).sum() <= 1
    assert bank.n_added_.sum() > 20
    _assert_equals_batch_posterior(bank, streams, u, n, seed=6)
    with pytest.raises(ValueError, match="max_inducing_candidates"):
        AFVSGPBank.from_learners(_learners(streams[:1], u), max_inducing_candidates=0)


def test_shared_ring_step_equals_the_per_learner_step():
    """Learners at one ring position take the window step with basic slicing; a bank whose
    rings are apart (one more learner that skipped its first sample) takes the per-learner
    indexed step, and its first four learners are the same bit for bit through the window
    filling (fitted on 10 of P samples), wrapping and inducing changes (same arithmetic,
    other indexing; the numpy paths: the compiled core's step is compared with them in
    test_afvsgp_bank_compiled.py). Which step a bank takes is not public: ``_synced`` is
    read to know that both were taken."""
    n = 4 * P
    streams = _streams(n)
    u = streams[0][1]
    # no periodic rebuild of [r, S] in the run (the banks stagger them by their sizes)
    learners = _learners(streams, u, n_fit=10, refresh_every=10**6)
    shared = AFVSGPBank.from_learners(learners, backend="numpy")
    apart = AFVSGPBank.from_learners(learners + learners[:1], backend="numpy")
    rows, xs = np.arange(K), np.random.default_rng(4).normal(size=(K, 3))
    for i in range(10, n):
        xi, z = _rows(streams, i)
        shared.update(xi, u[i], z)
        apart.update(np.vstack([xi, xi[:1]]), u[i], np.r_[z, np.nan if i == 10 else z[0]])
        if i % 5 == 0 or i == n - 1:
            for a, b in zip(shared.predict_affine(xs, rows), apart.predict_affine(xs, rows),
                            strict=True):
                np.testing.assert_array_equal(a, b)
    assert shared._synced and not apart._synced
    assert shared.n_added_.min() > 0
    np.testing.assert_array_equal(shared.n_added_, apart.n_added_[:K])
    for k in range(K):
        for a, b in ((shared.statistics(k), apart.statistics(k)),
                     (shared.inducing(k), apart.inducing(k))):
            for x, y in zip(a, b, strict=True):
                np.testing.assert_array_equal(x, y)
