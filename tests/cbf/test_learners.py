"""Learner registry and the controller's warm-up / online learning with every GP learner."""

import numpy as np
import pytest

from afvsgp_gym.cbf import LEARNERS, REGISTRY, SafetyController, make_learner

#: the learners that run on any layout (the shared one needs projected barriers)
LEARNING = tuple(n for n in LEARNERS
                 if REGISTRY[n].gp_class is not None and not REGISTRY[n].projected)


def test_registry_names():
    assert LEARNERS == ("none", "oracle", "gp", "vsgp", "sogp", "afvsgp", "afvsgp-shared")


@pytest.mark.parametrize("name", LEARNING)
def test_make_learner_fits_predicts_and_updates(name):
    """Every learner the filter can use: ``fit`` and ``update`` return the learner; the affine
    prediction (eq. 20) has the shapes of the filter's program, a symmetric positive
    semidefinite covariance and, on data following ``z = 1 + 2 u_1 - u_2``, that law's
    coefficients; one new sample above the data moves the mean at its point up."""
    rng = np.random.default_rng(0)
    xi, u = rng.normal(size=(60, 3)), rng.uniform(-1, 1, size=(60, 2))
    z = 1.0 + u @ np.array([2.0, -1.0]) + 0.01 * rng.normal(size=60)
    learner = make_learner(name, action_dim=2, **({} if name == "gp" else {"num_inducing": 15}))
    assert learner.fit(xi, u, z) is learner
    b, sig = learner.predict_affine(xi[:5])
    assert b.shape == (5, 3) and sig.shape == (5, 3, 3)
    np.testing.assert_allclose(sig, sig.transpose(0, 2, 1), rtol=1e-12, atol=1e-15)
    scale = np.abs(sig).max()
    assert np.linalg.eigvalsh(sig).min() >= -1e-9 * scale
    # the law's coefficients, to 5 % of the smallest (the data's noise is 0.01)
    np.testing.assert_allclose(b, np.tile([1.0, 2.0, -1.0], (5, 1)), atol=0.05)
    ubar = np.concatenate([[1.0], u[0]])
    before = float(learner.predict_affine(xi[:1])[0][0] @ ubar)
    assert learner.update(xi[0], u[0], z[0] + 1.0) is learner
    after = float(learner.predict_affine(xi[:1])[0][0] @ ubar)
    assert after > before + 0.01, (before, after)


@pytest.mark.parametrize("name", ["none", "oracle"])
def test_make_learner_refuses_names_without_a_gp(name):
    with pytest.raises(ValueError, match=name):
        make_learner(name, action_dim=2)


def test_make_learner_unknown_name_lists_valid():
    valid = r"\['none', 'oracle', 'gp', 'vsgp', 'sogp', 'afvsgp', 'afvsgp-shared'\]"
    with pytest.raises(ValueError, match=valid):
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
    # after warm-up the learned Delta B (eq. 51) is the truth's at visited states, for the
    # action applied and for any other action: the model error's dependence on the action
    # (the gain error) is learned, not only its value along the path
    probe_u = np.random.default_rng(9).uniform(-1, 1, size=(5, 2))
    applied, anywhere = [], []
    for res, nom, true in out[60:]:
        b, sig = ctrl.bank.predict_affine(nom.xi[None], np.array([0]))
        assert np.all(np.isfinite(sig)) and np.all(np.abs(res.u) <= 1)
        for u, rows in ((res.u, applied), *((p, anywhere) for p in probe_u)):
            truth = (true.lf + true.lg @ u) - (nom.lf + nom.lg @ u)
            rows.append((b[0] @ np.concatenate([[1.0], u]), truth))
    for rows, tol in ((applied, 0.1), (anywhere, 0.35)):
        pred, truth = np.array(rows).T
        rmse = np.sqrt(np.mean((pred - truth) ** 2))
        # against the truth's own scale: its size along the path (a zero model's error: the
        # nominal model alone), its spread over actions (a constant model's error)
        ref = np.sqrt(np.mean(truth**2)) if rows is applied else np.std(truth)
        assert rmse < tol * ref, (name, rmse, ref)


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


def test_online_exploration_only_where_the_uncertainty_decides(disc):
    """After warm-up a proposal with no barrier near (or a confident model) passes unchanged;
    near a barrier where the model is uncertain and the margin small, it is excited."""
    ctrls = {}
    for noise in (0.0, 0.05):
        ctrl = SafetyController(
            -np.ones(2), np.ones(2), learner="afvsgp", warmup_samples=30, seed=0,
            online_exploration=noise, activation_distance=0.5,
            learner_kwargs={"num_inducing": 10},
        )
        _drive(disc, ctrl, 31, np.random.default_rng(2))
        ctrls[noise] = ctrl
    template = disc().terms()[0]
    far = type(template)(np.array([5.0, 0.0]), 0.0, np.zeros(2), template.xi)
    unseen = 40.0 * np.ones_like(template.xi)  # far from every sample: prior uncertainty
    near = type(template)(np.array([0.05, -0.1]), 0.0, np.zeros(2), unseen)
    u = np.array([0.3, -0.2])
    for ctrl in ctrls.values():
        res = ctrl.filter(u, [far])
        assert not res.warmup and res.n_active == 0
        np.testing.assert_array_equal(res.u, u)  # nothing near: untouched either way
    quiet, excited = ctrls[0.0].filter(u, [near]), ctrls[0.05].filter(u, [near])
    assert quiet.n_active == excited.n_active == 1
    assert not np.allclose(quiet.u, excited.u)  # the noisy proposal was filtered instead


def test_relative_gain_uncertainty_against_its_definition():
    """rho = sqrt(E||H e||^2) / ||H a|| for e ~ N(0, Sigma_uu): the closed form against the
    trace written out and a large-sample mean; zero gain gives inf, NaN stays NaN."""
    from afvsgp_gym.cbf.exploration import relative_gain_uncertainty

    rng = np.random.default_rng(3)
    m = 3
    root = rng.normal(size=(m + 1, m + 1))
    sigma = (root @ root.T)[None]
    gain = np.array([[0.5, -2.0, 1.0]])
    half = np.array([1.0, 10.0, 0.1])
    rho = relative_gain_uncertainty(sigma, gain, half)
    suu = sigma[0, 1:, 1:]
    expected = np.sqrt(sum(half[i] ** 2 * suu[i, i] for i in range(m))) / np.sqrt(
        sum((half[i] * gain[0, i]) ** 2 for i in range(m)))
    np.testing.assert_allclose(rho, [expected], rtol=1e-14)
    draws = rng.multivariate_normal(np.zeros(m), suu, size=200_000) * half
    mc = np.sqrt(np.mean(np.sum(draws**2, axis=1))) / np.linalg.norm(half * gain[0])
    np.testing.assert_allclose(rho[0], mc, rtol=0.01)  # 200k draws: ~0.2 % standard error
    assert relative_gain_uncertainty(sigma, np.zeros((1, m)), half)[0] == np.inf
    assert np.isnan(relative_gain_uncertainty(sigma, np.full((1, m), np.nan), half)[0])


def test_online_exploration_smaller_where_the_gain_is_known():
    """The same uncertain, deciding barrier: the exploration noise shrinks with the relative
    uncertainty of the action gain (a large known gain), and is capped at online_exploration."""
    ctrl = SafetyController(-np.ones(2), np.ones(2), learner="afvsgp", warmup_samples=30, seed=0,
                            online_exploration=0.4, learner_kwargs={"num_inducing": 10})
    rows = np.array([0])
    sig = np.diag([1.0, 0.01, 0.01])[None]  # std of the gain 0.1 per action
    u = np.zeros(2)
    a0 = np.array([-1.0])  # deciding: the mean margin is negative
    ctrl.bank.noise_variance = lambda rows: np.full(len(rows), 1e-4)  # uncertain

    def spread(gain: np.ndarray) -> float:
        ctrl.reseed(7)
        return float(np.std([ctrl._excite(u, rows, sig, a0, gain) for _ in range(2000)]))

    big, small = spread(np.array([[100.0, 0.0]])), spread(np.array([[0.01, 0.0]]))
    # rho = sqrt(0.02) / 100 and sqrt(0.02) / 0.01 (capped at 1): std 0.4 rho and 0.4
    np.testing.assert_allclose(small, 0.4, rtol=0.05)
    np.testing.assert_allclose(big, 0.4 * np.sqrt(0.02) / 100.0, rtol=0.05)


def test_exploration_scale_is_clipped_and_nan_means_full_noise():
    """perturb's scale: above 1 (or inf, or NaN from an undefined rho) gives the full online
    noise, at most 0 none; the same seeded draw either way."""
    from afvsgp_gym.cbf.exploration import Exploration

    def draw(scale: float) -> np.ndarray:
        ex = Exploration(-np.ones(3), np.ones(3), 0.3, 0.2, seed=0)
        ex.reseed(5)
        return ex.perturb(np.zeros(3), warm=False, scale=scale)

    full = draw(1.0)
    assert np.all(np.isfinite(full)) and np.any(full != 0.0)
    for scale in (2.0, np.inf, np.nan):
        np.testing.assert_array_equal(draw(scale), full)
    np.testing.assert_array_equal(draw(0.5), draw(1.0) * 0.5)
    for scale in (0.0, -1.0):
        np.testing.assert_array_equal(draw(scale), np.zeros(3))
