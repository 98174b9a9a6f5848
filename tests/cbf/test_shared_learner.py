"""The shared learner (issue 45): projected barriers in the layout, the ProjectedBank's exact
linear map of its learners' predictions, and the controller's checks."""

import numpy as np
import pytest

from afvsgp_gym.cbf import SafetyController
from afvsgp_gym.cbf.learners import ProjectedBank, make_bank
from afvsgp_gym.types import BarrierLayout, BarrierSet

#: two "joints" (learners 0 and 1, each with a + and a - barrier), then three projected
#: "obstacle pairs" whose model error is a linear map of the joints'
LAYOUT = BarrierLayout(np.array([2, 2, 2, 2, 2, 2, 2]), np.array([0, 0, 1, 1, -1, -1, -1]),
                       np.array([1.0, -1.0, 1.0, -1.0, 1.0, 1.0, 1.0]), np.array([1, 1]))
M = 2  # actions


def _fitted_bank(seed=0):
    """A ProjectedBank on LAYOUT fitted to two affine joint laws (the projected barriers'
    datasets are never read)."""
    rng = np.random.default_rng(seed)
    bank = make_bank("afvsgp-shared", len(LAYOUT), M, {"num_inducing": 12}, layout=LAYOUT)
    assert isinstance(bank, ProjectedBank)
    xi, u = rng.normal(size=(80, 3)), rng.uniform(-1, 1, size=(80, M))
    laws = (1.0 + u @ np.array([2.0, -1.0]), -0.5 + u @ np.array([0.3, 1.5]))
    data = []
    for lrn, sign in zip(LAYOUT.learner, LAYOUT.sign, strict=True):
        z = sign * laws[lrn] if lrn >= 0 else np.full(80, np.nan)  # projected: never read
        data.append((xi, u, z + 0.01 * rng.normal(size=80)))
    bank.fit(data)
    return bank, xi


def test_layout_with_projected_barriers():
    assert LAYOUT.n_learners == 2 and not LAYOUT.one_to_one
    np.testing.assert_array_equal(LAYOUT.representatives, [0, 2])
    np.testing.assert_array_equal(LAYOUT.projected, [False] * 4 + [True] * 3)
    # a projected barrier first: the learners still number in order of first appearance
    lay = BarrierLayout(np.full(3, 2), np.array([-1, 0, 0]), np.ones(3), np.zeros(1, int))
    np.testing.assert_array_equal(lay.representatives, [1])


@pytest.mark.parametrize(
    ("learner", "sign", "match"),
    [([-1, -1], [1.0, 1.0], "order of first"),       # no learner at all
     ([0, -2], [1.0, 1.0], "order of first"),        # -1 is the only mark
     ([0, -1], [1.0, -1.0], "sign")],                # a projected barrier's sign is +1
)
def test_bad_projected_layouts_are_refused(learner, sign, match):
    with pytest.raises(ValueError, match=match):
        BarrierLayout(np.full(2, 2), np.array(learner), np.array(sign), np.zeros(1, int))


def test_projected_prediction_is_the_exact_linear_map_of_the_learners():
    """b_k = W_k @ b_l and Sigma_k = sum_l W_kl^2 Sigma_l for the projected barriers; the
    learners' own barriers get their learner's prediction with the sign applied (as the
    MappedBank); the result does not depend on which rows are asked together."""
    bank, xi = _fitted_bank()
    K = len(LAYOUT)
    xis = np.tile(xi[3], (K, 1))
    W = np.zeros((K, 2))
    W[4:] = [[0.7, -0.2], [0.0, 1.3], [-2.0, 0.5]]
    b_l, s_l = bank.bank.predict_affine(xis[LAYOUT.representatives], np.arange(2))
    rows = np.arange(K)
    b, s = bank.predict_projected(xis, W, rows)
    np.testing.assert_allclose(b[4:], W[4:] @ b_l, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(s[4:], np.einsum("kl,lij->kij", W[4:] ** 2, s_l),
                               rtol=1e-12, atol=1e-14)
    for k in range(4):
        np.testing.assert_allclose(b[k], LAYOUT.sign[k] * b_l[LAYOUT.learner[k]], rtol=1e-12)
        np.testing.assert_allclose(s[k], s_l[LAYOUT.learner[k]], rtol=1e-12)
    b2, s2 = bank.predict_projected(xis, W, np.array([5, 1]))
    np.testing.assert_allclose(b2, b[[5, 1]], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(s2, s[[5, 1]], rtol=1e-12, atol=1e-14)
    # only own barriers asked: the mapped path, same numbers
    b3, _ = bank.predict_projected(xis, W, np.array([2, 3]))
    np.testing.assert_allclose(b3, b[[2, 3]], rtol=1e-12)
    # the learned laws come through (the data's noise is 0.01)
    np.testing.assert_allclose(b_l, [[1.0, 2.0, -1.0], [-0.5, 0.3, 1.5]], atol=0.05)


def test_projected_noise_variance_and_update_mask():
    bank, xi = _fitted_bank()
    K = len(LAYOUT)
    s2 = bank.bank.noise_variance(np.arange(2))
    assert np.all(np.isnan(bank.noise_variance(np.arange(K))[4:]))  # before any prediction
    W = np.zeros((K, 2))
    W[4:] = [[0.7, -0.2], [0.0, 1.3], [-2.0, 0.5]]
    bank.predict_projected(np.tile(xi[0], (K, 1)), W, np.arange(K))
    nv = bank.noise_variance(np.arange(K))
    np.testing.assert_allclose(nv[:4], s2[LAYOUT.learner[:4]], rtol=1e-12)
    np.testing.assert_allclose(nv[4:], W[4:] ** 2 @ s2, rtol=1e-12)
    z = np.array([0.1, -0.1, 0.2, -0.2, np.nan, np.nan, np.nan])  # projected: not read
    done = bank.update(np.tile(xi[1], (K, 1)), np.array([0.2, -0.4]), z)
    assert done.shape == (K,) and done.all()


def _terms(rng, projection=True):
    K = len(LAYOUT)
    d = np.column_stack([np.full(K, 0.05), np.zeros(K)])
    W = np.zeros((K, 2))
    W[4:] = rng.normal(size=(3, 2))
    return BarrierSet(d, np.zeros(K), rng.normal(size=(K, M)), np.tile(rng.normal(size=3),
                      (K, 1)), projection=W if projection else None)


def test_controller_needs_the_projection_and_a_projected_layout():
    rng = np.random.default_rng(1)
    ctrl = SafetyController(-np.ones(M), np.ones(M), n_barriers=len(LAYOUT), layout=LAYOUT,
                            learner="afvsgp-shared", relative_degree=2, warmup_samples=5)
    with pytest.raises(ValueError, match="terms.projection must have shape"):
        ctrl.filter(np.zeros(M), _terms(rng, projection=False))
    ctrl.filter(np.zeros(M), _terms(rng))  # with it: fine
    with pytest.raises(ValueError, match="projected barriers"):
        SafetyController(-np.ones(M), np.ones(M), n_barriers=3, learner="afvsgp-shared")
