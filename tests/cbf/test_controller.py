"""SafetyController with the nominal-only and oracle learners on an independent simulator."""

import numpy as np
import pytest

from afvsgp_gym.cbf import LEARNERS, SafetyController
from afvsgp_gym.types import BarrierTerms


def _run(disc, learner, steps=250, **kw):
    sim = disc(gain=0.5, wind=(0.15, 0.0))
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner=learner, alpha=1.5, **kw)
    hs, results = [], []
    for _ in range(steps):
        terms = sim.terms()
        u_nom = sim.nominal()
        u_nom_copy = u_nom.copy()
        res = ctrl.filter(u_nom, terms, true_terms=sim.terms("true"))
        np.testing.assert_array_equal(u_nom, u_nom_copy)  # never mutated
        assert np.all(np.isfinite(res.u)) and np.all(np.abs(res.u) <= 1)
        hs.append(sim.step(res.u))
        ctrl.observe(terms, res.u, sim.terms(), sim.dt)
        results.append(res)
    return np.array(hs), results


def test_none_violates_and_oracle_is_safe(disc):
    h_none, _ = _run(disc, "none")
    h_oracle, res = _run(disc, "oracle")
    assert h_none.min() < 0
    assert h_oracle.min() >= 0
    assert any(r.active for r in res) and all(r.feasible for r in res)
    assert all(np.all(r.delta_b_std == 0) for r in res)


def test_no_learner_no_warmup(disc):
    _, res = _run(disc, "none", steps=5)
    assert not any(r.warmup for r in res)


def test_unknown_learner_lists_valid_names():
    with pytest.raises(ValueError, match="afvsgp") as exc:
        SafetyController(-np.ones(2), np.ones(2), learner="nope")
    for name in LEARNERS:
        assert name in str(exc.value)


def test_oracle_needs_true_terms():
    ctrl = SafetyController(-np.ones(1), np.ones(1), learner="oracle")
    t = [BarrierTerms(np.ones(2), 0.0, np.ones(1), np.zeros(1))]
    with pytest.raises(ValueError, match="true_terms"):
        ctrl.filter(np.zeros(1), t)


@pytest.mark.parametrize("field", ["derivatives", "lf", "lg", "xi"])
def test_nan_terms_give_flagged_fallback(field):
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none")
    vals = {
        "derivatives": np.array([0.1, -0.5]),
        "lf": 0.0,
        "lg": np.array([1.0, 0.0]),
        "xi": np.zeros(3),
    }
    vals[field] = np.full_like(np.atleast_1d(vals[field]), np.nan)
    if field == "lf":
        vals[field] = float("nan")
    res = ctrl.filter(np.array([-1.0, 0.0]), [BarrierTerms(**vals)])
    assert not res.feasible and res.status == "invalid_input"
    assert np.all(np.isfinite(res.u)) and np.all(np.abs(res.u) <= 1)


@pytest.mark.parametrize("field", ["derivatives", "xi"])
def test_observe_skips_and_counts_non_finite_samples(field):
    """A learning controller (in its warm-up, then fitted) skips a sample whose measurement
    or features are not finite: counted in ``n_skipped_samples``, left out of the fit data and
    of the online updates, never raised."""
    rng = np.random.default_rng(0)
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="afvsgp", warmup_samples=20,
                            learner_kwargs={"num_inducing": 5})

    def terms(bad=False):
        vals = {"derivatives": rng.normal(size=2), "lf": 0.0, "lg": np.zeros(2),
                "xi": rng.normal(size=3)}
        if bad:
            vals[field] = np.full(len(vals[field]), np.nan)
        return [BarrierTerms(**vals)]

    for step in range(19):  # warm-up: 19 samples, 3 of them bad
        bad = step in (2, 9, 15)
        z = ctrl.observe(terms(), rng.uniform(-1, 1, 2), terms(bad), 0.01)
        assert np.isnan(z[0]) == bad
    assert ctrl.n_skipped_samples == 3 and ctrl.warming_up
    xi, u, z = ctrl.dataset()[0]
    assert xi.shape == (16, 3) and u.shape == (16, 2) and np.all(np.isfinite(z))
    ctrl.observe(terms(), np.zeros(2), terms(), 0.01)  # the 20th sample: the fit
    assert not ctrl.warming_up and ctrl.n_update_failures == 0
    probe = rng.normal(size=(1, 3))
    before = ctrl.bank.predict_affine(probe, np.array([0]))
    z = ctrl.observe(terms(), np.zeros(2), terms(bad=True), 0.01)  # after the fit
    assert np.isnan(z[0]) and ctrl.n_skipped_samples == 4 and ctrl.learner_error is None
    for a, b in zip(ctrl.bank.predict_affine(probe, np.array([0])), before, strict=True):
        np.testing.assert_array_equal(a, b)  # the skipped sample did not reach the learner


def test_nan_action_gives_flagged_fallback():
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none")
    t = [BarrierTerms(np.array([1.0, 0.0]), 0.0, np.array([1.0, 0.0]), np.zeros(3))]
    res = ctrl.filter(np.array([np.nan, 0.0]), t)
    assert not res.feasible and np.all(np.isfinite(res.u))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_barriers": 0}, "n_barriers"),
        ({"activation_distance": np.nan}, "activation_distance"),
        ({"activation_distance": -0.1}, r"activation_distance must be >= 0"),
        ({"residual_correction": 1.0}, "residual_correction"),
        ({"beta": -1.0}, "beta"),
        ({"warmup_samples": 1}, "warmup_samples"),
        ({"exploration_noise": -0.1}, "exploration_noise"),
        ({"alpha": 0.0}, "alpha"),
        ({"learner": "none", "learner_kwargs": {"x": 1}}, "learner_kwargs"),
        ({"learner": "afvsgp", "learner_kwargs": {"num_inducing": 0}}, "num_inducing"),
        ({"learner": "afvsgp", "learner_kwargs": {"forgetting": 1.5}}, "forgetting"),
        ({"learner": "vsgp", "learner_kwargs": {"noise_variance": -1.0}}, "noise_variance"),
        ({"learner": "gp", "learner_kwargs": {"max_iter": 0}}, "max_iter"),
        ({"online_exploration": -1.0}, "online_exploration"),
        ({"noise_floor": 0.1}, "unknown option.*noise_floor"),
        ({"barrier_margin": -1.0}, "barrier_margin"),
        ({"kernel_init": "magic"}, "unknown option.*kernel_init"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SafetyController(-np.ones(2), np.ones(2), **kwargs)


def test_programs_are_built_ahead_up_to_a_cap_then_on_demand():
    """The constructor builds the solvers of programs up to ``PREPARED_PROGRAM_SIZES``
    barriers; ``prepare_programs()`` builds every size (a real-time loop's call); a bad size
    is refused by name."""
    from afvsgp_gym.cbf.controller import PREPARED_PROGRAM_SIZES

    n = PREPARED_PROGRAM_SIZES + 5
    ctrl = SafetyController(-np.ones(2), np.ones(2), n, learner="afvsgp")
    built = ctrl.socp.programs._solvers
    assert {k for _, k in built} == set(range(1, PREPARED_PROGRAM_SIZES + 1))
    assert {kind for kind, _ in built} == {"qp", "socp"}
    ctrl.prepare_programs()
    assert {k for _, k in built} == set(range(1, n + 1))
    assert len(built) == 2 * n
    with pytest.raises(ValueError, match="n_constraints"):
        ctrl.prepare_programs(0)
