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


def _learners(streams, u, **kw):
    opts = dict(num_inducing=8, window=P, forgetting=0.95, add_threshold=0.05, swap_margin=0.0)
    opts.update(kw)
    out = []
    for k, (xi, _, z, _) in enumerate(streams):
        ker = ADPKernel(np.full((3, 3), 1.0 + 0.2 * k), np.array([1.0, 0.6, 0.4]))
        out.append(AFVSGP(ker, 0.0025 * (k + 1), **opts).fit(xi[:P], u[:P], z[:P], False))
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
        m = bank.n_inducing_[k]
        kern = bank.kernels[k]
        bref, sref = weighted_titsias_affine(
            kern.lengthscales, kern.variances, bank.noise_variance[k], xi[n - P : n],
            u[n - P : n], z[n - P : n], w, bank._ind_xi[k, :m], bank._ind_ub[k, :m, 1:],
            xs[k : k + 1], jitter=bank.jitter[k])
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
    for k in (1, 2):  # untouched learners: identical state
        np.testing.assert_array_equal(bank._stats[k], before._stats[k])
        assert bank._count[k] == before._count[k] and bank.n_seen_[k] == before.n_seen_[k]
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
    """Learners at one ring position take the window step with basic slicing; forcing the
    per-learner indexed step on a copy gives the same state bit for bit, through the window
    filling, wrapping and inducing changes (same arithmetic, other indexing). One skipped
    sample leaves the rings apart and the bank on the per-learner step (the numpy paths; the
    compiled core's step is compared with them in test_afvsgp_bank_compiled.py)."""
    n = 4 * P
    streams = _streams(n)
    u = streams[0][1]
    bank = AFVSGPBank.from_learners(_learners(streams, u), backend="numpy")
    bank._count[:], bank._head[:] = 10, 9  # windows part filled: filling, then wrapping
    bank._stagger()
    assert bank._synced
    ref = copy.deepcopy(bank)
    ref._synced = False
    for i in range(P, n):
        xi, z = _rows(streams, i)
        bank.update(xi, u[i], z)
        ref.update(xi, u[i], z)
        ref._synced = False
    assert bank._synced and bank.n_added_.min() > 0
    for name, value in vars(ref).items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(getattr(bank, name), value, err_msg=name)
    xi, z = _rows(streams, 5)
    z[2] = np.nan
    bank.update(xi, u[5], z)
    assert not bank._synced
