"""Barriers of mixed relative degrees sharing learners (BarrierLayout, MappedBank), the
per-barrier filter options and the warm-up around the backup."""

import numpy as np
import pytest

from afvsgp_gym.cbf import FilterConfig, SafetyController
from afvsgp_gym.cbf.learners import MappedBank
from afvsgp_gym.cbf.measurement import measure_samples
from afvsgp_gym.types import BarrierLayout, BarrierSet

#: two joint-like barriers sharing one learner (+, -), one speed-like barrier of degree 1 on
#: it, and an independent obstacle-like barrier: three barriers on learner 0, one on learner 1
LAYOUT = BarrierLayout(np.array([2, 2, 1, 2]), np.array([0, 0, 0, 1]),
                       np.array([1.0, -1.0, -1.0, 1.0]), np.array([0, 1]))


@pytest.mark.parametrize(
    ("args", "match"),
    [((np.array([2, 0]), np.arange(2), np.ones(2), np.zeros(2, int)), "relative_degree"),
     ((np.array([2, 2]), np.array([1, 0]), np.ones(2), np.zeros(2, int)), "order of first"),
     ((np.array([2, 2]), np.array([0, 0]), np.array([-1.0, 1.0]), np.zeros(1, int)), "sign"),
     ((np.array([2, 2]), np.array([0, 0]), np.array([1.0, 0.5]), np.zeros(1, int)), "sign"),
     ((np.array([2, 2]), np.array([0, 1]), np.ones(2), np.zeros(1, int)), "group")],
)
def test_bad_layouts_are_refused(args, match):
    with pytest.raises(ValueError, match=match):
        BarrierLayout(*args)


def test_layout_properties():
    assert LAYOUT.n_learners == 2 and LAYOUT.max_degree == 2
    np.testing.assert_array_equal(LAYOUT.representatives, [0, 3])
    assert not LAYOUT.is_uniform and not LAYOUT.one_to_one
    assert BarrierLayout.uniform(3, 2).is_uniform


def test_measurement_differences_each_barriers_own_highest_derivative():
    """z_k = (d_{r_k - 1}(t + dt) - d_{r_k - 1}(t)) / dt - mean nominal, per barrier."""
    rng = np.random.default_rng(0)
    before = BarrierSet(rng.normal(size=(4, 2)), rng.normal(size=4), rng.normal(size=(4, 3)),
                        rng.normal(size=(4, 5)))
    after = BarrierSet(rng.normal(size=(4, 2)), rng.normal(size=4), rng.normal(size=(4, 3)),
                       rng.normal(size=(4, 5)))
    u, dt = rng.normal(size=3), 0.01
    xi, z, bad = measure_samples(before, u, after, dt, LAYOUT.relative_degree)
    assert bad == 0
    for k, r in enumerate(LAYOUT.relative_degree):
        nominal = 0.5 * (before.lf[k] + before.lg[k] @ u + after.lf[k] + after.lg[k] @ u)
        expected = (after.derivatives[k, r - 1] - before.derivatives[k, r - 1]) / dt - nominal
        np.testing.assert_allclose(z[k], expected, rtol=1e-14)
    np.testing.assert_allclose(xi, 0.5 * (before.xi + after.xi), rtol=1e-15)


def _shared_data(rng, n=120):
    """Samples of Delta B_0 = 1 + 0.5 u_0 - q_0 and Delta B_1 = -2 u_1 (per learner)."""
    xi = rng.uniform(-1, 1, (n, 4))
    u = rng.uniform(-1, 1, (n, 2))
    z0 = 1.0 + 0.5 * u[:, 0] - xi[:, 0] + 0.01 * rng.normal(size=n)
    z1 = -2.0 * u[:, 1] + 0.01 * rng.normal(size=n)
    return xi, u, z0, z1


def test_shared_learner_predicts_each_barrier_with_its_sign():
    """A learner serving several barriers gives each the learner's prediction with the mean's
    sign flipped where the barrier's sign is -1 (the covariance unchanged); the learner is
    fitted on its representative's samples only (the others' are ignored, whatever they
    hold), and equals a plain learner fitted on the same data."""
    rng = np.random.default_rng(1)
    xi, u, z0, z1 = _shared_data(rng)
    signs = LAYOUT.sign
    junk = rng.normal(size=len(z0))  # barriers 1, 2: not read
    datasets = [(xi, u, z0), (xi, u, junk), (xi, u, junk), (xi, u, z1)]
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=4, learner="gp", layout=LAYOUT,
                            dataset=datasets, shared_hyperparameters=False)
    assert isinstance(ctrl.bank, MappedBank)
    plain = SafetyController(-np.ones(2), np.ones(2), n_barriers=2, learner="gp",
                             dataset=[(xi, u, z0), (xi, u, z1)], shared_hyperparameters=False)
    x = np.array([[0.2, 0.1, -0.3, 0.5]] * 4)
    b, sigma = ctrl.bank.predict_affine(x, np.arange(4))
    b_ref, s_ref = plain.bank.predict_affine(x[:2], np.arange(2))
    for k, learner in enumerate(LAYOUT.learner):
        np.testing.assert_allclose(b[k], signs[k] * b_ref[learner], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sigma[k], s_ref[learner], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b[0], [1.0 - 0.2, 0.5, 0.0], atol=0.05)  # it learned
    np.testing.assert_array_equal(ctrl.bank.noise_variance(np.array([1, 2, 3])),
                                  plain.bank.noise_variance(np.array([0, 0, 1])))


def test_mixed_layout_runs_the_filter_and_learns_online():
    """A fitted AFVSGP controller over the mixed layout: filter and observe run, every
    barrier gets the prediction of its learner, and updates reach both learners."""
    rng = np.random.default_rng(2)
    xi, u, z0, z1 = _shared_data(rng)
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=4, learner="afvsgp",
                            layout=LAYOUT, dataset=[(xi, u, z0), (xi, u, -z0), (xi, u, -z0),
                                                    (xi, u, z1)],
                            learner_kwargs={"num_inducing": 10, "window": 60})
    terms = BarrierSet(np.array([[0.5, -0.1], [0.4, 0.1], [0.3, 0.0], [0.2, -0.3]]),
                       np.zeros(4), np.zeros((4, 2)), np.tile([0.1, 0.0, 0.2, -0.1], (4, 1)))
    res = ctrl.filter(np.array([0.5, -0.5]), terms)
    assert res.feasible and np.all(np.isfinite(res.delta_b_mean))
    np.testing.assert_allclose(res.delta_b_mean[1], -res.delta_b_mean[0], rtol=1e-12)
    np.testing.assert_allclose(res.delta_b_std[:3], res.delta_b_std[0], rtol=1e-12)
    inner = ctrl.bank.bank.bank  # MappedBank -> AFVSGPLearnerBank -> AFVSGPBank
    seen = inner.n_seen_.copy()
    after = BarrierSet(terms.derivatives + 0.01, np.zeros(4), np.zeros((4, 2)), terms.xi)
    ctrl.observe(terms, res.u, after, 0.01)
    np.testing.assert_array_equal(inner.n_seen_, seen + 1)


def test_controller_refuses_a_layout_that_does_not_fit():
    with pytest.raises(ValueError, match="layout"):
        SafetyController(-np.ones(2), np.ones(2), n_barriers=3, layout=LAYOUT)
    with pytest.raises(ValueError, match="relative degree"):
        SafetyController(-np.ones(2), np.ones(2), n_barriers=4, layout=LAYOUT,
                         relative_degree=3)


@pytest.mark.parametrize(
    ("options", "match"),
    [({"activation_distance": -0.1}, "activation_distance"),
     ({"activation_distance": (0.1, np.nan)}, r"activation_distance\[1\]"),
     ({"braking_deceleration": 0.0}, "braking_deceleration"),
     ({"braking_deceleration": (5.0, -1.0)}, r"braking_deceleration\[1\]"),
     ({"first_gain": (1.0, np.inf)}, r"first_gain\[1\]"),
     ({"warmup_exploration": "policy"}, "warmup_exploration")],
)
def test_bad_per_barrier_options_name_the_option_and_entry(options, match):
    with pytest.raises(ValueError, match=match):
        FilterConfig(**options)


def test_per_barrier_options_must_have_one_value_per_barrier():
    with pytest.raises(ValueError, match="activation_distance must be one value or 4"):
        SafetyController(-np.ones(2), np.ones(2), n_barriers=4, layout=LAYOUT,
                         activation_distance=(0.1, 0.2))
    cfg = FilterConfig(activation_distance=np.array([0.1, np.inf]))
    assert cfg.activation_distance == (0.1, np.inf)
    np.testing.assert_array_equal(cfg.per_barrier("activation_distance", 2), [0.1, np.inf])
    np.testing.assert_array_equal(FilterConfig().per_barrier("braking_deceleration", 3),
                                  [np.inf] * 3)


@pytest.mark.parametrize("mode", ["proposal", "backup"])
def test_warmup_explores_around_the_proposal_or_the_backup(mode):
    """Without noise the warm-up applies the proposal (the paper) or the backup (whatever the
    policy proposes); after warm-up the policy acts again."""
    layout = BarrierLayout.uniform(1, 2)
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=1, layout=layout,
                            learner="afvsgp", warmup_samples=5, exploration_noise=0.0,
                            online_exploration=0.0, warmup_exploration=mode,
                            learner_kwargs={"num_inducing": 4, "window": 20})
    backup = np.array([0.25, -0.5])
    rng = np.random.default_rng(3)
    h = 1.0
    for step in range(8):
        terms = BarrierSet(np.array([[h, 0.0]]), np.zeros(1), np.zeros((1, 2)),
                           rng.normal(size=(1, 3)))
        proposal = np.array([0.8, 0.6])
        res = ctrl.filter(proposal, terms, u_backup=lambda: backup)
        expected = backup if (mode == "backup" and res.warmup) else proposal
        np.testing.assert_array_equal(res.u, expected)
        after = BarrierSet(terms.derivatives, np.zeros(1), np.zeros((1, 2)),
                           rng.normal(size=(1, 3)))
        ctrl.observe(terms, res.u, after, 0.01)
        if step == 7:
            assert not res.warmup
