"""Learner registry and the controller's warm-up / online learning with every GP learner."""

import numpy as np
import pytest

from afvsgp_gym.cbf import LEARNERS, REGISTRY, SafetyController, make_learner

LEARNING = tuple(n for n in LEARNERS if REGISTRY[n].gp_class is not None)


def test_registry_names():
    assert LEARNERS == ("none", "oracle", "gp", "vsgp", "sogp", "afvsgp")


@pytest.mark.parametrize("name", LEARNING)
def test_make_learner_interface(name):
    learner = make_learner(name, action_dim=2)
    for method in ("fit", "update", "predict_affine"):
        assert callable(getattr(learner, method))


@pytest.mark.parametrize("name", ["none", "oracle"])
def test_make_learner_refuses_names_without_a_gp(name):
    with pytest.raises(ValueError, match=name):
        make_learner(name, action_dim=2)


def test_make_learner_unknown_name_lists_valid():
    with pytest.raises(ValueError, match=r"\['none', 'oracle', 'gp', 'vsgp', 'sogp', 'afvsgp'\]"):
        make_learner("gpr", action_dim=2)


def _drive(disc, ctrl, steps, rng):
    sim = disc(gain=0.6, wind=(0.2, -0.1))
    sim.p = np.array([-1.2, 0.05])
    out = []
    for _ in range(steps):
        terms = sim.terms()
        res = ctrl.filter(sim.nominal((1.0, 0.0)) + 0.2 * rng.standard_normal(2), terms)
        sim.step(res.u)
        ctrl.observe(terms, res.u, sim.terms(), sim.dt)
        out.append((res, terms[0], sim.terms("true")[0]))
    return out


@pytest.mark.parametrize("name", LEARNING)
def test_warmup_then_online_learning(disc, name):
    rng = np.random.default_rng(0)
    kw = {"num_inducing": 10} if name in ("vsgp", "afvsgp", "sogp") else {}
    ctrl = SafetyController(
        -np.ones(2), np.ones(2), learner=name, warmup_samples=40, seed=0, learner_kwargs=kw
    )
    assert ctrl.warming_up
    out = _drive(disc, ctrl, 80, rng)
    assert all(r.warmup for r, _, _ in out[:40]) and not any(r.warmup for r, _, _ in out[41:])
    assert ctrl.n_update_failures == 0 and ctrl.last_error is None
    # after warm-up the learned Delta B (eq. 51) tracks the truth at visited states
    errs, stds = [], []
    for res, nom, true in out[60:]:
        b, sig = ctrl.bank.predict_affine(nom.xi[None], np.array([0]))
        ubar = np.concatenate([[1.0], res.u])
        truth = (true.lf + true.lg @ res.u) - (nom.lf + nom.lg @ res.u)
        errs.append(b[0] @ ubar - truth)
        stds.append(np.sqrt(ubar @ sig[0] @ ubar))
        assert np.all(np.isfinite(res.u)) and np.all(np.abs(res.u) <= 1)
    assert np.sqrt(np.mean(np.square(errs))) < 0.3
    assert np.all(np.isfinite(stds))


def test_dataset_option_skips_warmup(disc):
    rng = np.random.default_rng(1)
    rec = SafetyController(-np.ones(2), np.ones(2), learner="afvsgp", warmup_samples=10**6)
    _drive(disc, rec, 60, rng)
    data = rec.dataset()
    assert data[0][0].shape == (60, 4) and data[0][1].shape == (60, 2)
    ctrl = SafetyController(
        -np.ones(2),
        np.ones(2),
        learner="afvsgp",
        dataset=data[0],
        learner_kwargs={"num_inducing": 10},
    )
    assert not ctrl.warming_up
    res = ctrl.filter(np.zeros(2), [_drive(disc, rec, 1, rng)[0][1]])
    assert not res.warmup and np.all(res.delta_b_std > 0)


def test_frozen_learning_keeps_model():
    ctrl = SafetyController(-np.ones(1), np.ones(1), learner="afvsgp", warmup_samples=10**6)
    ctrl.learning = False
    assert ctrl.warming_up  # warm-up still collects: learning=False only freezes online updates


def test_online_exploration_only_perturbs_when_enabled(disc):
    rng = np.random.default_rng(2)
    for noise in (0.0, 0.05):
        ctrl = SafetyController(
            -np.ones(2),
            np.ones(2),
            learner="afvsgp",
            warmup_samples=30,
            online_exploration=noise,
            learner_kwargs={"num_inducing": 10},
        )
        _drive(disc, ctrl, 31, rng)
        far = disc().terms()[0]
        far = type(far)(np.array([5.0, 0.0]), 0.0, np.zeros(2), far.xi)  # h = 5: inactive
        res = ctrl.filter(np.array([0.3, -0.2]), [far])
        assert not res.warmup
        assert np.array_equal(res.u, [0.3, -0.2]) == (noise == 0.0)
