"""Backup action on infeasibility and the residual correction (disturbance observer)."""

import numpy as np
import pytest

from afvsgp_gym.cbf import SafetyController, SOCPFilter
from afvsgp_gym.types import BarrierTerms

# nominal "zero" model: lg = 0, so with h' << 0 no action can satisfy the constraint
_INFEASIBLE = [BarrierTerms(np.array([0.05, -2.0]), 0.0, np.zeros(2), np.zeros(3))]
_SAFE = [BarrierTerms(np.array([1.0, 0.0]), 0.0, np.zeros(2), np.zeros(3))]


def test_backup_action_replaces_infeasible_solution():
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none", alpha=2.0)
    res = ctrl.filter(np.array([0.3, 0.1]), _INFEASIBLE, u_backup=np.array([-3.0, 0.4]))
    assert not res.feasible and res.status.startswith("backup:")
    np.testing.assert_array_equal(res.u, [-1.0, 0.4])  # clipped to the bounds
    assert res.active


def test_backup_callable_is_only_called_when_needed():
    calls = []

    def brake():
        calls.append(1)
        return np.array([0.5, -0.5])

    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none", alpha=2.0)
    res = ctrl.filter(np.array([0.3, 0.1]), _SAFE, u_backup=brake)
    assert res.feasible and not calls
    res = ctrl.filter(np.array([0.3, 0.1]), _INFEASIBLE, u_backup=brake)
    assert len(calls) == 1 and res.status.startswith("backup:")


@pytest.mark.parametrize("bad", [np.array([np.nan, 0.0]), np.zeros(3), lambda: 1 / 0])
def test_unusable_backup_falls_back_to_max_margin(bad):
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none", alpha=2.0)
    with_bad = ctrl.filter(np.array([0.3, 0.1]), _INFEASIBLE, u_backup=bad)
    plain = ctrl.filter(np.array([0.3, 0.1]), _INFEASIBLE)
    assert with_bad.status.startswith("fallback:") and not with_bad.feasible
    np.testing.assert_allclose(with_bad.u, plain.u)
    assert np.all(np.isfinite(with_bad.u)) and np.all(np.abs(with_bad.u) <= 1)


def test_nan_terms_with_backup_apply_the_backup():
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none")
    bad = [BarrierTerms(np.array([np.nan, 0.0]), 0.0, np.zeros(2), np.zeros(3))]
    res = ctrl.filter(np.zeros(2), bad, u_backup=np.array([0.2, 0.2]))
    assert not res.feasible and res.status == "backup:invalid_input"
    np.testing.assert_array_equal(res.u, [0.2, 0.2])


#: The nominal HOCBF constraint ``c0 + c u >= 0`` of ``_fitted_controller`` (alpha = 2 for
#: both class-K gains, relative degree 2), worked by hand: psi_1 = h' + 2 h, psi_2 = psi_1' +
#: 2 psi_1 = h'' + 4 h' + 4 h with h'' = lf + lg u, less the barrier margin 1e-3 times
#: d psi_2 / d h = 4.
def _nominal_c0(h, hd, lf=0.0):
    return lf + 4.0 * hd + 4.0 * h - 4e-3


def _fitted_controller(w, rng, **options):
    """AFVSGP fitted offline on z = 1 + u . (2, -1) with frozen online learning."""
    xi = rng.normal(size=(120, 3))
    u = rng.uniform(-1, 1, size=(120, 2))
    z = 1.0 + u @ np.array([2.0, -1.0]) + 0.05 * rng.normal(size=120)
    return SafetyController(
        -np.ones(2), np.ones(2), learner="afvsgp", alpha=2.0, residual_correction=w,
        dataset=(xi, u, z), online=False, online_exploration=0.0, seed=0,
        learner_kwargs={"num_inducing": 10}, **options,
    )


def test_residual_bias_is_the_exponential_average_of_the_residuals():
    rng = np.random.default_rng(0)
    w = 0.2
    ctrl = _fitted_controller(w, rng, activation_distance=0.5)
    terms = [BarrierTerms(np.array([0.1, 0.0]), 0.0, np.zeros(2), np.array([0.1, 0.2, 0.3]))]
    expected = 0.0
    offsets = [-3.0, -3.0, -1.0, 2.0, -3.0]
    for off in offsets:
        res = ctrl.filter(np.array([0.2, -0.1]), terms)
        ubar = np.concatenate([[1.0], res.u])
        b, _ = ctrl.bank.predict_affine(terms[0].xi[None], np.array([0]))
        z = float(b[0] @ ubar) + off  # measured = learned mean + offset
        # eq. 48 with r = 2, zero nominal: z = (h'_after - h'_before) / dt
        after = [BarrierTerms(np.array([0.1, z * 0.01]), 0.0, np.zeros(2), terms[0].xi)]
        ctrl.observe(terms, res.u, after, 0.01)
        expected = (1 - w) * expected + w * off
    assert ctrl.residual_bias[0] == pytest.approx(expected, abs=1e-6)
    ctrl.reset_residuals()
    assert ctrl.residual_bias[0] == 0.0
    # a barrier outside the cone program (h above the activation distance) is not predicted:
    # its observer restarts from zero
    ctrl.residual_bias[:] = 1.0
    far = [BarrierTerms(np.array([1.0, 0.0]), 0.0, np.zeros(2), terms[0].xi)]
    res = ctrl.filter(np.array([0.2, -0.1]), far)
    assert res.n_active == 0 and np.isnan(res.delta_b_mean[0])
    ctrl.observe(far, res.u, far, 0.01)
    assert ctrl.residual_bias[0] == 0.0


def test_residual_bias_shifts_the_constraint_mean():
    """The filtered action equals an independent SOCP whose a0 carries the bias."""
    rng = np.random.default_rng(1)
    ctrl = _fitted_controller(0.2, rng)
    ctrl.residual_bias[:] = -4.0
    terms = [BarrierTerms(np.array([0.05, -0.3]), 0.0, np.zeros(2), np.array([0.1, 0.2, 0.3]))]
    u_nom = np.array([-0.5, 0.5])
    res = ctrl.filter(u_nom, terms)
    b, sig = ctrl.bank.predict_affine(terms[0].xi[None], np.array([0]))
    a0 = _nominal_c0(0.05, -0.3) + b[0, 0] - 4.0  # lg = 0: the gain is the learned one alone
    # any factor with G'G = beta^2 Sigma gives the cone (eq. 05); the eigen-factor here, the
    # controller's is Cholesky's
    w, v = np.linalg.eigh(0.5 * (sig[0] + sig[0].T))
    G = (2.5 * np.sqrt(np.maximum(w, 0)))[:, None] * v.T  # beta = 2.5, the default
    ref = SOCPFilter(-np.ones(2), np.ones(2)).solve(u_nom, [a0], b[:, 1:], G[None])
    assert res.status == ref.status
    np.testing.assert_allclose(res.u, ref.u, atol=1e-7)
    unbiased = _fitted_controller(0.2, np.random.default_rng(1)).filter(u_nom, terms)
    assert not np.allclose(unbiased.u, res.u)


def test_residual_correction_option_is_checked():
    with pytest.raises(ValueError, match="residual_correction"):
        SafetyController(-np.ones(2), np.ones(2), residual_correction=1.0)


def test_controller_deepcopies_and_pickles_with_its_state():
    """The clarabel solver objects are not picklable: SOCPFilter drops them from its state and
    rebuilds them, so a copied controller continues like the original, bit for bit (no data
    equilibration: an answer does not depend on which solver object computed it)."""
    import copy
    import pickle

    rng = np.random.default_rng(2)
    ctrl = _fitted_controller(0.2, rng)
    ctrl.residual_bias[:] = -2.0
    terms = [BarrierTerms(np.array([0.05, -0.3]), 0.0, np.zeros(2), np.array([0.1, 0.2, 0.3]))]
    ctrl.filter(np.array([-0.5, 0.5]), terms)  # builds a solver object
    for clone in (copy.deepcopy(ctrl), pickle.loads(pickle.dumps(ctrl))):
        for u_nom in rng.uniform(-1, 1, size=(5, 2)):
            a, b = ctrl.filter(u_nom, terms), clone.filter(u_nom, terms)
            assert a.status == b.status
            np.testing.assert_array_equal(a.u, b.u)


@pytest.mark.parametrize("relax", [True, False])
def test_infeasible_chance_constraint_relaxes_to_the_mean(relax):
    """beta so large that no action meets the chance constraint, while the mean constraint
    (beta = 0) is satisfiable: the mean-only solution is applied (flagged), else the backup."""
    rng = np.random.default_rng(4)
    ctrl = _fitted_controller(0.0, rng, beta=200.0, relax_to_mean=relax)
    far = np.array([4.0, -4.0, 4.0])  # away from the data: the posterior std is large
    terms = [BarrierTerms(np.array([0.05, 0.0]), 0.0, np.zeros(2), far)]
    res = ctrl.filter(np.array([-1.0, 1.0]), terms, u_backup=np.array([0.5, 0.5]))
    assert not res.feasible
    if relax:
        assert res.status.startswith("relaxed:")
        b, _ = ctrl.bank.predict_affine(terms[0].xi[None], np.array([0]))
        a0 = _nominal_c0(0.05, 0.0) + b[0, 0]  # lg = 0: the gain is the learned one alone
        assert a0 + b[0, 1:] @ res.u >= -1e-6  # the mean constraint holds
        assert res.margins[0] < 0  # the chance constraint does not
    else:
        assert res.status.startswith("backup:")
        np.testing.assert_array_equal(res.u, [0.5, 0.5])


def _mixed_controller(rng, **options):
    """Two barriers learned from z = 1 + u . (2, -1): barrier 0 of relative degree 2,
    barrier 1 of relative degree 1 (as a joint speed), fitted offline, frozen."""
    from afvsgp_gym.types import BarrierLayout

    xi = rng.normal(size=(120, 3))
    u = rng.uniform(-1, 1, size=(120, 2))
    z = 1.0 + u @ np.array([2.0, -1.0]) + 0.05 * rng.normal(size=120)
    layout = BarrierLayout(np.array([2, 1]), np.array([0, 1]), np.ones(2), np.zeros(2, int))
    return SafetyController(
        -np.ones(2), np.ones(2), n_barriers=2, learner="afvsgp", layout=layout, alpha=2.0,
        dataset=(xi, u, z), online=False, online_exploration=0.0, residual_correction=0.0,
        seed=0, learner_kwargs={"num_inducing": 10}, **options)


def _mixed_terms(xi_speed):
    far = np.array([4.0, -4.0, 4.0])  # away from the data: the posterior std is large
    return [BarrierTerms(np.array([0.05, 0.0]), 0.0, np.zeros(2), far),
            BarrierTerms(np.array([0.3, 0.0]), 0.0, np.zeros(2), xi_speed)]


def test_relaxation_keeps_the_band_of_relative_degree_one():
    """The relaxed program drops the band of the degree-2 barrier only: the degree-1
    barrier's chance constraint holds at the relaxed action."""
    ctrl = _mixed_controller(np.random.default_rng(4), beta=60.0, relax_to_mean=True)
    near = np.zeros(3)  # in the data: a small std, its band can be met
    res = ctrl.filter(np.array([-1.0, 1.0]), _mixed_terms(near), u_backup=np.array([0.5, 0.5]))
    assert res.status.startswith("relaxed:")
    assert res.margins[1] >= -1e-6  # the speed-like barrier's band kept
    assert res.margins[0] < 0  # the other's chance constraint relaxed


def test_relaxation_that_cannot_keep_the_degree_one_band_brakes():
    """Both barriers far from the data: the degree-1 band cannot be met, so the relaxation
    is infeasible and the backup acts (dropping every band would have been feasible)."""
    ctrl = _mixed_controller(np.random.default_rng(4), beta=200.0)
    far = np.array([4.0, -4.0, 4.0])
    res = ctrl.filter(np.array([-1.0, 1.0]), _mixed_terms(far), u_backup=np.array([0.5, 0.5]))
    assert res.status.startswith("backup:")
    np.testing.assert_array_equal(res.u, [0.5, 0.5])
    mean_only = ctrl.socp.solve(np.array([-1.0, 1.0]), *_mean_constraints(ctrl, far), None,
                                None)
    assert mean_only.feasible


def _mean_constraints(ctrl, far):
    """The two barriers' mean-only constraints ``a0 + a u >= 0`` (learned mean, no band)."""
    bset_terms = _mixed_terms(far)
    c0, c = ctrl.constraints(bset_terms)
    b, _ = ctrl.bank.predict_affine(np.array([t.xi for t in bset_terms]), np.arange(2))
    c0 = c0 - ctrl.config.barrier_margin * ctrl.barriers.margin_gain
    return c0 + b[:, 0], c + b[:, 1:]
