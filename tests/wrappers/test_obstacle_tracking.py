"""The filter's view of the obstacles through the env's camera: the stated sensing back-off
holds with the probability it states, the Kalman estimate beats the raw reading, and the raw
baseline trusts what it reads."""

import gymnasium as gym
import numpy as np
import pytest
from scipy import stats

import afvsgp_gym  # noqa: F401
from afvsgp_gym.cbf import SafetyController
from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.wrappers import SafetyFilter

STATIC = "afvsgp_gym/FrankaObstacleStatic-v0"
DYNAMIC = "afvsgp_gym/FrankaObstacleDynamic-v0"


def test_sensing_std_is_the_gradient_of_the_linear_chain():
    """For the paper's linear chain ``c0 = lf + (a1 + a2) h' + a1 a2 h`` the sensing std is
    ``sqrt(g' C g)`` with ``g = (a1 a2, a1 + a2, 1)`` (the differences are exact up to
    rounding for an affine map)."""
    rng = np.random.default_rng(0)
    k = 5
    ctrl = SafetyController(-np.ones(2), np.ones(2), n_barriers=k, relative_degree=2,
                            learner="none", alpha=(3.0, 5.0))
    root = rng.normal(size=(k, 3, 3))
    cov = root @ root.transpose(0, 2, 1)
    terms = BarrierSet(rng.normal(size=(k, 2)), rng.normal(size=k), rng.normal(size=(k, 2)),
                       np.zeros((k, 1)), cov)
    g = np.array([15.0, 8.0, 1.0])
    expected = np.sqrt(np.einsum("i,kij,j->k", g, cov, g))
    np.testing.assert_allclose(ctrl.sensing_std(terms), expected, rtol=1e-7)
    bad = BarrierSet(terms.derivatives, terms.lf, terms.lg, terms.xi, cov[:, :2, :2])
    with pytest.raises(ValueError, match="covariance"):
        ctrl.sensing_std(bad)


def test_the_back_off_moves_the_action_by_beta_std():
    """One barrier, one action: the filtered action sits ``beta std / c`` inside the exact
    program's boundary."""
    ctrl = SafetyController(np.array([-10.0]), np.array([10.0]), n_barriers=1,
                            relative_degree=2, learner="none", alpha=(1.0, 1.0), beta=2.0,
                            barrier_margin=0.0)
    derivs = np.array([[0.5, 0.0]])
    exact = BarrierSet(derivs, np.array([-4.0]), np.array([[1.0]]), np.zeros((1, 1)))
    cov = np.zeros((1, 3, 3))
    cov[0, 2, 2] = 0.25  # lf's std 0.5
    sensed = BarrierSet(derivs, exact.lf, exact.lg, exact.xi, cov)
    u_exact = ctrl.filter(np.array([-10.0]), exact).u[0]
    u_sensed = ctrl.filter(np.array([-10.0]), sensed).u[0]
    assert u_exact == pytest.approx(3.5, abs=1e-6)  # -4 + u + 0.5 >= 0
    assert u_sensed - u_exact == pytest.approx(2.0 * 0.5, abs=1e-6)


@pytest.mark.parametrize("beta", [1.0, 2.0])
def test_the_stated_sensing_probability_holds_on_the_arm(beta):
    """The hand near the static obstacle: obstacle estimates drawn from their covariance
    (1 cm, 5 cm/s per axis, correlated); the true constraint of the nearest pair falls below
    the estimate's ``c0 - beta std`` in ``Phi(-beta)`` of the draws, within a 4-sigma
    binomial band (first order is accurate at these 1 cm errors a few cm from contact)."""
    env = SafetyFilter(gym.make(STATIC, obstacle_noise=0.01), learner="oracle")
    base = env.unwrapped
    env.reset(seed=0)
    po = base._obstacle_states[0][0]
    q = fm.Q_HOME.copy()
    base.set_state(q, np.zeros(7))
    # move the hand's spheres toward the obstacle: the nearest pair a few cm away
    hand = base.n_obstacle_barriers
    for _ in range(200):
        h = base.true_state_terms("true").h[:hand]
        if h.min() < 0.04:
            break
        jac = base._spheres[2][int(np.argmin(h))][:, :7]
        direction = po - base._spheres[0][int(np.argmin(h))]
        q = q + 0.02 * np.linalg.pinv(jac) @ direction
        base.set_state(q, np.full(7, 0.05))
    true_terms = base.true_state_terms("true")
    c0_true = env.controller.constraints(true_terms)[0][:hand]
    row = int(np.argmin(true_terms.h[:hand]))
    per_axis = np.array([[1e-4, 1e-4, 0.0], [1e-4, 2.5e-3, 0.0], [0.0, 0.0, 0.0]])
    root = np.linalg.cholesky(per_axis[:2, :2])
    rng = np.random.default_rng(1)
    n, misses = 3000, 0
    for _ in range(n):
        err = root @ rng.standard_normal((2, 3))  # rows: position, velocity errors
        base.set_obstacle_estimate(po[None] + err[0], err[1][None], np.zeros((1, 3)),
                                   per_axis[None])
        sensed = base.barrier_terms("true")
        c0 = env.controller.constraints(sensed)[0][row]
        std = env.controller.sensing_std(sensed)[row]
        misses += c0_true[row] < c0 - beta * std
    p = stats.norm.sf(beta)
    assert abs(misses / n - p) < 4 * np.sqrt(p * (1 - p) / n)


def test_the_kalman_estimate_beats_the_raw_reading():
    """Dynamic scene, 1 cm, 30 Hz, 60 ms: over the obstacle's move the estimate's centre error
    (``info["obstacle_estimate_error"]``) is well below the raw reading's
    (``info["obstacle_error"]``, which lags by the speed times the latency and age); the raw
    baseline's terms carry no covariance and the estimate's do."""
    kwargs = {"obstacle_noise": 0.01, "obstacle_rate": 30.0, "obstacle_delay": 0.06,
              "self_collision": False}  # about the obstacle's estimate: its barriers only
    env = SafetyFilter(gym.make(DYNAMIC, **kwargs), learner="oracle")
    base = env.unwrapped
    env.reset(seed=0)
    raw, est = [], []
    zero = np.zeros(7, dtype=np.float32)
    for _ in range(2500):
        info = env.step(zero)[4]
        if np.linalg.norm(base._obstacle_states[0][1]) > 0.05:  # while it moves
            raw.append(info["obstacle_error"])
            est.append(info["obstacle_estimate_error"])
    assert len(raw) > 200
    assert np.mean(est) < 0.6 * np.mean(raw)
    assert base.barrier_terms("nominal").covariance is not None
    baseline = SafetyFilter(gym.make(DYNAMIC, **kwargs), learner="oracle",
                            obstacle_estimator="raw")
    baseline.reset(seed=0)
    assert baseline.tracking.estimator is None
    assert baseline.tracking.terms(baseline.unwrapped.barrier_terms("nominal")).covariance is None
    with pytest.raises(ValueError, match="obstacle_estimator"):
        SafetyFilter(gym.make(DYNAMIC, **kwargs), learner="oracle", obstacle_estimator="ukf")
    with pytest.raises(ValueError, match="estimator_process_std"):
        SafetyFilter(gym.make(DYNAMIC, **kwargs), learner="oracle", estimator_process_std=0.0)
