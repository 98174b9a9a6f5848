"""Eq. 48 measurement against the true model error of an independent simulator."""

import numpy as np
import pytest

from afvsgp_gym.cbf import measure
from afvsgp_gym.types import BarrierTerms


def test_measures_true_minus_nominal_second_derivative(disc):
    sim = disc(gain=0.6, wind=(0.3, -0.2), dt=0.01)
    rng = np.random.default_rng(0)
    errs, scale = [], []
    for _ in range(150):
        u = np.clip(sim.nominal() + 0.3 * rng.standard_normal(2), -1, 1)
        before, before_true = sim.terms()[0], sim.terms("true")[0]
        sim.step(u)
        after, after_true = sim.terms()[0], sim.terms("true")[0]
        xi, z = measure(before, u, after, sim.dt)
        delta_mid = 0.5 * (
            (before_true.lf + before_true.lg @ u - before.lf - before.lg @ u)
            + (after_true.lf + after_true.lg @ u - after.lf - after.lg @ u)
        )
        np.testing.assert_allclose(xi, 0.5 * (before.xi + after.xi))
        errs.append(z - delta_mid)
        scale.append(delta_mid)
    # the finite difference error is far below the size of the model error
    assert np.max(np.abs(errs)) < 0.02 * np.std(scale) + 1e-3
    assert np.std(scale) > 0.05


def test_exact_for_constant_second_derivative():
    # h = 0.5 c t^2: h' changes by c dt exactly; nominal says lf0 = 0.2, lg0 = 0
    c, dt = 1.3, 0.05
    b = BarrierTerms(np.array([1.0, 0.4]), 0.2, np.zeros(1), np.ones(2))
    a = BarrierTerms(np.array([1.0, 0.4 + c * dt]), 0.2, np.zeros(1), 3 * np.ones(2))
    xi, z = measure(b, np.zeros(1), a, dt)
    np.testing.assert_allclose(z, c - 0.2)
    np.testing.assert_allclose(xi, [2.0, 2.0])


@pytest.mark.parametrize("dt", [0.0, -1.0, np.nan])
def test_bad_dt(dt):
    t = BarrierTerms(np.zeros(2), 0.0, np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="dt"):
        measure(t, np.zeros(1), t, dt)


def test_matches_point_mass_delta_b_true():
    """Against the env's ground truth (true minus nominal h'' for the applied action)."""
    from afvsgp_gym.envs.point_mass import PointMassObstacleEnv

    env = PointMassObstacleEnv(nominal_model="zero")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    errs, truth = [], []
    for _ in range(300):
        u = rng.uniform(-1, 1, 2)
        before = env.barrier_terms("nominal")[0]
        _, _, _, _, info = env.step(u.astype(np.float32))
        after = env.barrier_terms("nominal")[0]
        _, z = measure(before, u.astype(np.float32).astype(float), after, env.dt)
        errs.append(z - info["delta_b_true"][0])
        truth.append(info["delta_b_true"][0])
    errs, truth = np.array(errs), np.array(truth)
    # pre-step truth vs midpoint measurement: O(dt) apart, small against the uncertainty scale
    assert np.sqrt(np.mean(errs**2)) < 0.05 * np.std(truth)
