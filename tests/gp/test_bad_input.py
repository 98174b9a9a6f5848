"""Bad input for every learner: ValueError naming the argument, state unchanged after a
rejected update; jittered Cholesky warns instead of failing; no NaN predictions."""

import numpy as np
import pytest
from gp_batch_formulas import synthetic
from tolerances import gamma, warned_jitter

from afvsgp_gym.gp import AFVSGP, SOGP, VSGP, ADPKernel, ExactGP
from afvsgp_gym.gp._linalg import jittered_cholesky

B, M_ACT = 3, 2


def _kernel():
    return ADPKernel(np.full((M_ACT + 1, B), 1.2), np.array([1.0, 0.5, 0.3]))


LEARNERS = {
    "exact": lambda: ExactGP(_kernel(), 0.01),
    "vsgp": lambda: VSGP(_kernel(), 0.01, num_inducing=8),
    "afvsgp": lambda: AFVSGP(_kernel(), 0.01, num_inducing=8, window=30),
    "sogp": lambda: SOGP(_kernel(), 0.01, num_inducing=8, batch_size=1),
}


@pytest.fixture(params=sorted(LEARNERS))
def fitted(request):
    rng = np.random.default_rng(0)
    xi, u, z, _ = synthetic(rng, 40)
    return LEARNERS[request.param]().fit(xi, u, z, learn_hyperparameters=False)


GOOD = (np.zeros(B), np.zeros(M_ACT), 0.5)
BAD_UPDATES = [
    ("xi", (np.zeros(B + 1), GOOD[1], GOOD[2])),
    ("xi", (np.zeros((1, B)), GOOD[1], GOOD[2])),
    ("xi", (np.array([0.0, np.nan, 0.0]), GOOD[1], GOOD[2])),
    ("xi", (np.array([0.0, np.inf, 0.0]), GOOD[1], GOOD[2])),
    ("u", (GOOD[0], np.zeros(M_ACT + 1), GOOD[2])),
    ("u", (GOOD[0], np.array([np.nan, 0.0]), GOOD[2])),
    ("u", (GOOD[0], np.array([0.0, -np.inf]), GOOD[2])),
    ("z", (GOOD[0], GOOD[1], np.nan)),
    ("z", (GOOD[0], GOOD[1], np.inf)),
    ("z", (GOOD[0], GOOD[1], np.zeros(2))),
    ("z", (GOOD[0], GOOD[1], "a")),
]


@pytest.mark.parametrize("name,args", BAD_UPDATES, ids=[f"{n}{i}" for i, (n, _) in
                                                       enumerate(BAD_UPDATES)])
def test_rejected_update_names_argument_and_leaves_state_unchanged(fitted, name, args):
    xs = np.random.default_rng(1).normal(size=(4, B))
    before = fitted.predict_affine(xs)
    seen = fitted.n_seen_ if hasattr(fitted, "n_seen_") else None
    with pytest.raises(ValueError, match=name):
        fitted.update(*args)
    after = fitted.predict_affine(xs)
    for a, b in zip(after, before, strict=True):
        np.testing.assert_array_equal(a, b)
    if seen is not None:
        assert fitted.n_seen_ == seen
    fitted.update(*GOOD)  # still usable
    assert all(np.all(np.isfinite(a)) for a in fitted.predict_affine(xs))


@pytest.mark.parametrize("name", sorted(LEARNERS))
@pytest.mark.parametrize("arg,mutate", [
    ("xi", lambda xi, u, z: (xi[:, :2], u, z)),
    ("u", lambda xi, u, z: (xi, u[:-1], z)),
    ("z", lambda xi, u, z: (xi, u, z[:-1])),
    ("xi", lambda xi, u, z: (np.where(np.arange(len(xi))[:, None] == 3, np.nan, xi), u, z)),
    ("u", lambda xi, u, z: (xi, np.where(np.arange(len(u))[:, None] == 3, np.inf, u), z)),
    ("z", lambda xi, u, z: (xi, u, np.where(np.arange(len(z)) == 3, np.nan, z))),
])
def test_fit_rejects_bad_data_naming_argument(name, arg, mutate):
    rng = np.random.default_rng(2)
    xi, u, z, _ = synthetic(rng, 20)
    with pytest.raises(ValueError, match=arg):
        LEARNERS[name]().fit(*mutate(xi, u, z), learn_hyperparameters=False)


def test_predict_rejects_bad_input_naming_argument(fitted):
    with pytest.raises(ValueError, match="xi"):
        fitted.predict_affine(np.zeros((2, B + 1)))
    with pytest.raises(ValueError, match="xi"):
        fitted.predict_affine(np.full((1, B), np.nan))
    with pytest.raises(ValueError, match="xi"):
        fitted.predict(np.zeros((2, B - 1)), np.zeros((2, M_ACT)))
    with pytest.raises(ValueError, match="u"):
        fitted.predict(np.zeros((2, B)), np.zeros((3, M_ACT)))


def test_predictions_are_finite_and_sigma_psd_far_from_data(fitted):
    xs = np.array([[1e3, -1e3, 0.0], [0.0, 0.0, 0.0]])
    bvec, sig = fitted.predict_affine(xs)
    assert np.all(np.isfinite(bvec)) and np.all(np.isfinite(sig))
    np.testing.assert_array_equal(sig, sig.transpose(0, 2, 1))  # every learner symmetrises
    # PSD up to the cancellation of its terms (at most N = 40 training samples or M = 8
    # inducing points: gamma(40) of the prior variances) and eigvalsh's gamma(3)
    top = np.max(np.abs(sig))
    assert np.linalg.eigvalsh(sig).min() >= -(4 * gamma(40) + 3 * gamma(3)) * top
    mean, var = fitted.predict(xs, np.ones((2, M_ACT)))
    assert np.all(np.isfinite(mean)) and np.all(var >= 0)


def test_jittered_cholesky_retries_and_warns():
    v = np.array([[1.0], [2.0], [3.0]])
    a = v @ v.T  # rank one
    with pytest.warns(RuntimeWarning, match="jitter") as record:
        low = jittered_cholesky(a, name="test")
    assert np.all(np.isfinite(low))
    # L L' = a + jitter I up to Cholesky's backward error gamma(n + 1) |L| |L'|; the warning
    # prints the jitter to 3 significant digits
    extra = warned_jitter(record)
    err = np.abs(low @ low.T - a - extra * np.eye(3))
    assert np.all(err <= 1e-3 * extra + gamma(4) * np.abs(low) @ np.abs(low.T))


def test_duplicate_inducing_points_warn_and_stay_finite():
    rng = np.random.default_rng(3)
    xi, u, z, _ = synthetic(rng, 30)
    ind = (np.vstack([xi[:4], xi[:1]]), np.vstack([u[:4], u[:1]]))  # a duplicate
    with pytest.warns(RuntimeWarning, match="jitter"):
        gp = VSGP(_kernel(), 0.01, inducing=ind, jitter=0.0).fit(xi, u, z, False)
    bvec, sig = gp.predict_affine(xi[:3])
    assert np.all(np.isfinite(bvec)) and np.all(np.isfinite(sig))


@pytest.mark.parametrize("kwargs", [dict(forgetting=0.0), dict(forgetting=1.5),
                                    dict(window=0), dict(num_inducing=0),
                                    dict(add_threshold=-1.0)])
def test_afvsgp_rejects_bad_parameters_at_fit(kwargs):
    rng = np.random.default_rng(4)
    xi, u, z, _ = synthetic(rng, 20)
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=name):
        AFVSGP(_kernel(), 0.01, **kwargs).fit(xi, u, z, False)


def test_unfitted_learner_raises():
    for make in LEARNERS.values():
        with pytest.raises((RuntimeError, ValueError)):
            make().predict_affine(np.zeros((1, B)))
