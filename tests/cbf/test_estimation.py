"""The obstacle Kalman filter (afvsgp_gym.cbf.estimation): its discrete model against Van
Loan's integral, its steps against a full-state textbook filter, its statistical consistency
(NEES) with delayed samples, delay compensation, steady states, and its bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import cholesky, expm, solve_discrete_are
from scipy.stats import chi2

from afvsgp_gym.cbf.estimation import (
    ESTIMATOR_MODELS,
    ObstacleEstimator,
    discrete_process_noise,
    transition,
)

SIZE = {"constant-velocity": 2, "constant-acceleration": 3}


def van_loan(dt: float, q: float, model: str) -> tuple[np.ndarray, np.ndarray]:
    """``F`` and ``Q`` of ``x' = A x + G w`` (A the shift, G = e_s, ``E[w w^T] = q delta``)
    from one matrix exponential (Van Loan 1978): ``expm([[-A, G q G^T], [0, A^T]] dt) =
    [[., F^-1 Q], [0, F^T]]``."""
    s = SIZE[model]
    a = np.diag(np.ones(s - 1), 1)
    g = np.zeros((s, 1))
    g[-1] = 1.0
    m = np.zeros((2 * s, 2 * s))
    m[:s, :s], m[:s, s:], m[s:, s:] = -a, q * g @ g.T, a.T
    b = expm(m * dt)
    f = b[s:, s:].T
    return f, f @ b[:s, s:]


# ----------------------------------------------------------------------------- discrete model


@pytest.mark.parametrize("model", ESTIMATOR_MODELS)
@pytest.mark.parametrize("dt", [1e-4, 1e-2, 1 / 30, 1.0])
def test_transition_and_process_noise_match_van_loan(model, dt):
    """``M`` is nilpotent (``M^(2s) = 0``), so expm's Pade approximant (degree >= 3, exact
    up to ``M^6``) is exact in exact arithmetic: only rounding remains, a few ulps per
    entry (observed below 1e-14 relative, entries from 5e-22 at dt = 1e-4 to 1), so 1e-12
    relative *per entry*, which also pins the tiny ``dt^5/20`` corner that a normwise
    tolerance would not."""
    q = 0.7 ** 2
    f_ref, q_ref = van_loan(dt, q, model)
    f = transition(dt, model)
    qd = discrete_process_noise(dt, 0.7, model)
    s = SIZE[model]
    assert f.shape == qd.shape == (s, s)
    upper = np.triu_indices(s)
    np.testing.assert_allclose(f[upper], f_ref[upper], rtol=1e-12, atol=0)
    assert np.all(f[np.tril_indices(s, -1)] == 0.0)
    np.testing.assert_allclose(qd, q_ref, rtol=1e-12, atol=0)
    assert np.array_equal(qd, qd.T)
    assert np.all(np.linalg.eigvalsh(qd / qd[-1, -1]) > 0)


@pytest.mark.parametrize("model", ESTIMATOR_MODELS)
def test_zero_step_is_the_identity(model):
    s = SIZE[model]
    assert np.array_equal(transition(0.0, model), np.eye(s))
    assert np.array_equal(discrete_process_noise(0.0, 2.0, model), np.zeros((s, s)))


@pytest.mark.parametrize("call, name", [
    (lambda: transition(-1e-3, "constant-velocity"), "dt"),
    (lambda: transition(np.nan, "constant-velocity"), "dt"),
    (lambda: transition(0.1, "cv"), "model"),
    (lambda: discrete_process_noise(0.1, -1.0, "constant-velocity"), "process_std"),
    (lambda: discrete_process_noise(np.inf, 1.0, "constant-acceleration"), "dt"),
])
def test_helpers_reject_bad_arguments(call, name):
    with pytest.raises(ValueError, match=name):
        call()


# ----------------------------------------------------------------- against a textbook filter


class FullStateKF:
    """One obstacle's textbook filter on the full state ``[p_xyz, v_xyz(, a_xyz)]``: explicit
    3-D matrices (kron with I3), the gain by a linear solve, ``P <- (I - K H) P``."""

    def __init__(self, model, sigma, q, iv, ia):
        self.model, self.q = model, q
        self.s = SIZE[model]
        self.h = np.kron(np.eye(1, self.s), np.eye(3))
        self.r = sigma ** 2 * np.eye(3)
        self.p0 = np.kron(np.diag([sigma ** 2, iv ** 2, ia ** 2][:self.s]), np.eye(3))
        self.x = self.p = None
        self.t = -np.inf

    def matrices(self, dt):
        q = self.q
        if self.model == "constant-velocity":
            f = np.array([[1.0, dt], [0.0, 1.0]])
            qa = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
        else:
            f = np.array([[1.0, dt, dt ** 2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            qa = q * np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6],
                               [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                               [dt ** 3 / 6, dt ** 2 / 2, dt]])
        return np.kron(f, np.eye(3)), np.kron(qa, np.eye(3))

    def predicted(self, t):
        f, qf = self.matrices(t - self.t)
        return f @ self.x, f @ self.p @ f.T + qf

    def update(self, z, t):
        if np.isnan(z).any() or t <= self.t:
            return
        if self.x is None:
            self.x = np.concatenate([z, np.zeros(3 * (self.s - 1))])
            self.p = self.p0.copy()
        else:
            x, p = self.predicted(t)
            s = self.h @ p @ self.h.T + self.r
            k = np.linalg.solve(s, self.h @ p).T
            self.x = x + k @ (z - self.h @ x)
            self.p = (np.eye(3 * self.s) - k @ self.h) @ p
        self.t = t


def _close(ours, ref):
    """Equal to 1e-10 relative to the reference's largest entry."""
    np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())


@pytest.mark.parametrize("model", ESTIMATOR_MODELS)
def test_matches_a_full_state_textbook_filter(model):
    """Irregular per-obstacle sample times, missing rows, repeats and stale samples, and a
    prediction after every update: the same state and the same covariance (``P kron I3``)."""
    rng = np.random.default_rng(7)
    o, sigma, q, iv, ia = 3, 0.02, 0.8, 0.5, 2.0
    est = ObstacleEstimator(o, sigma, process_std=np.sqrt(q), model=model,
                            initial_velocity_std=iv, initial_acceleration_std=ia)
    refs = [FullStateKF(model, sigma, q, iv, ia) for _ in range(o)]
    s = SIZE[model]
    clock = np.zeros(o)
    truth = rng.uniform(-1, 1, (o, 3))
    for step in range(120):
        clock += rng.uniform(0.005, 0.2, o)
        times = clock.copy()
        stale = rng.random(o) < 0.15
        times[stale] -= rng.uniform(0.0, 0.3, stale.sum())    # repeats and out of order
        truth += rng.normal(0, 0.05, (o, 3))
        z = truth + rng.normal(0, sigma, (o, 3))
        z[rng.random(o) < 0.2] = np.nan
        if step % 10 == 3:
            z[0, 1] = np.nan                                  # one NaN skips the row
        est.update(z, times)
        for i in range(o):
            refs[i].update(z[i], times[i])
        if not est.initialized:
            continue
        t = np.max(est.last_sample_time) + rng.uniform(0.0, 0.15)
        p, v, a, cov = est.predict(t)
        for i, ref in enumerate(refs):
            x_ref, p_ref = ref.predicted(t)
            ours = np.concatenate([p[i], v[i], a[i]])[:3 * s]
            _close(ours, x_ref)
            _close(np.kron(cov[i, :s, :s], np.eye(3)), p_ref)
        if s == 2:
            assert np.all(a == 0) and np.all(cov[:, 2] == 0) and np.all(cov[:, :, 2] == 0)
    assert est.initialized


# ------------------------------------------------------------------------------ consistency


@pytest.mark.parametrize("model", ESTIMATOR_MODELS)
def test_nees_is_chi_square_consistent_with_delayed_samples(model):
    """Truth drawn from the filter's own model (Van Loan's exact discretisation on the 240 Hz
    control grid; the prior of ``v`` (and ``a``) at the first sample as the filter assumes),
    a 30 Hz camera with 1 cm noise and 60 ms delay, the estimate predicted to the control
    time. The filter is then the exact posterior, so each run's per-axis NEES is
    chi-square with ``s`` degrees of freedom, independent over axes and runs: the sum over
    ``N`` runs and 3 axes is chi-square(3 s N). Checked at a few times, each inside the
    central chi-square interval at 1 - 0.001 / m (Bonferroni: all of them together at
    99.9 %). The ``N`` runs are the ``N`` obstacles of one estimator."""
    rng = np.random.default_rng(2024)
    n, sigma, w, iv, ia = 400, 0.01, 0.5, 0.5, 2.0
    rate, delay, control = 30, 0.06, 240               # Hz, s, Hz
    per_frame = control // rate                         # 8 control steps per camera frame
    s = SIZE[model]
    f, qd = van_loan(1.0 / control, w ** 2, model)
    lq = cholesky(qd, lower=True)
    est = ObstacleEstimator(n, sigma, process_std=w, model=model, initial_velocity_std=iv,
                            initial_acceleration_std=ia)
    x = np.zeros((n, s, 3))                             # truth per run: [p, v(, a)] x xyz
    x[:, 0] = rng.uniform(-1, 1, (n, 3))
    x[:, 1] = rng.normal(0, iv, (n, 3))
    if s == 3:
        x[:, 2] = rng.normal(0, ia, (n, 3))
    checks = [15, 30, 90, 300, 719]                     # control steps: 62.5 ms to 3 s
    level = 0.001 / len(checks)
    lo, hi = chi2.ppf([level / 2, 1 - level / 2], 3 * s * n) / (3 * n)
    frames = []
    nees = []
    for j in range(checks[-1] + 1):
        if j % per_frame == 0:                          # sample k = j / 8 taken now
            frames.append(x[:, 0] + rng.normal(0, sigma, (n, 3)))
        k = int(np.floor((j - delay * control) / per_frame))   # newest arrived by j / 240
        if k >= 0:
            est.update(frames[k], k / rate)
        if j in checks:
            p, v, a, cov = est.predict(j / control)
            e = np.stack([p, v, a][:s], axis=1) - x     # (n, s, 3)
            sol = np.linalg.solve(cov[:, :s, :s], e)
            nees.append(np.einsum("nsi,nsi->", e, sol) / (3 * n))
        x = f @ x + lq @ rng.standard_normal((n, s, 3))
    assert len(nees) == len(checks)
    for value in nees:
        assert lo < value < hi, (nees, lo, hi)


def test_delay_is_compensated_by_prediction():
    """A constant-velocity obstacle (no process noise in the truth), 1 mm noise, 30 Hz and
    100 ms delay: the prediction at the control time is within a few noise standard
    deviations of the truth (and within 4 of its own std), while the newest sample lags by
    ``v`` times its age (0.1 s here)."""
    rng = np.random.default_rng(3)
    sigma, delay, rate = 1e-3, 0.1, 30
    p0 = np.array([[0.4, -0.2, 0.6]])
    vel = np.array([[0.6, -0.4, 0.3]])
    est = ObstacleEstimator(1, sigma, process_std=0.01)
    samples = p0 + vel * (np.arange(91) / rate)[:, None] + rng.normal(0, sigma, (91, 3))
    for j in range(0, 3001):                            # 1 kHz control for 3 s
        t = j / 1000
        k = int(np.floor(round((t - delay) * rate, 9)))  # newest sample arrived by t
        if k >= 0:
            est.update(samples[[k]], k / rate)
    last = samples[[k]]
    t = 3.0
    assert est.last_sample_time[0] == pytest.approx(t - delay)
    truth = p0 + vel * t
    p, v, _, cov = est.predict(t)
    err = np.abs(p - truth)[0]
    assert np.all(err < 3 * sigma), err
    assert np.all(err < 4 * np.sqrt(cov[0, 0, 0])), (err, np.sqrt(cov[0, 0, 0]))
    np.testing.assert_allclose(v, vel, atol=0.02)
    lag = (truth - last)[0]
    np.testing.assert_allclose(lag, vel[0] * delay, atol=4 * sigma)
    assert np.all(np.abs(lag) > 10 * err)


def test_static_obstacle_matches_least_squares():
    """Negligible process noise: the filter is the batch least-squares line fit through the
    samples (``p`` flat, ``v`` with the filter's prior), so the position variance at the
    newest sample is ``c^T J^-1 c`` with ``J = X^T X / sigma^2 + diag(0, 1/iv^2)`` and
    ``c = [1, t_n]``, and it keeps falling, below ``sigma`` from the second sample on
    (about ``2 sigma / sqrt(n)``)."""
    rng = np.random.default_rng(5)
    sigma, iv, rate, n = 0.01, 3.0, 30, 300
    centre = np.array([[0.3, 0.1, -0.5]])
    est = ObstacleEstimator(1, sigma, process_std=1e-9, initial_velocity_std=iv)
    stds, zs = [], []
    for k in range(n):
        zs.append(centre[0] + rng.normal(0, sigma, 3))
        est.update(zs[-1][None], k / rate)
        stds.append(np.sqrt(est.predict(k / rate)[3][0, 0, 0]))
    stds = np.array(stds)
    assert stds[0] == pytest.approx(sigma, rel=1e-12)
    assert np.all(stds[1:] < sigma) and np.all(np.diff(stds) < 0)
    t = np.arange(n) / rate
    design = np.stack([np.ones(n), t], axis=1)
    info = design.T @ design / sigma ** 2 + np.diag([0.0, 1.0 / iv ** 2])
    c = np.array([1.0, t[-1]])
    var = c @ np.linalg.solve(info, c)
    assert stds[-1] ** 2 == pytest.approx(var, rel=1e-6)
    assert stds[-1] == pytest.approx(2 * sigma / np.sqrt(n), rel=0.02)
    theta = np.linalg.solve(info, design.T @ np.array(zs) / sigma ** 2)   # (2, 3)
    p, v, _, _ = est.predict(t[-1])
    np.testing.assert_allclose(p[0], c @ theta, atol=1e-9)
    np.testing.assert_allclose(v[0], theta[1], atol=1e-8)


@pytest.mark.parametrize("model", ESTIMATOR_MODELS)
def test_steady_state_is_the_riccati_solution(model):
    """With process noise, regular samples drive ``P`` to the discrete algebraic Riccati
    equation's fixed point (scipy's solver, from the Van Loan ``F``, ``Q``), below
    ``sigma^2`` in position."""
    sigma, w, rate = 0.01, 0.5, 30
    est = ObstacleEstimator(2, sigma, process_std=w, model=model)
    rng = np.random.default_rng(1)
    for k in range(600):
        est.update(rng.normal(0, sigma, (2, 3)), k / rate)
    cov = est.predict(599 / rate)[3]
    s = SIZE[model]
    f, qd = van_loan(1 / rate, w ** 2, model)
    h = np.eye(1, s)
    pp = solve_discrete_are(f.T, h.T, qd, np.array([[sigma ** 2]]))
    post = pp - pp @ h.T @ h @ pp / (pp[0, 0] + sigma ** 2)
    for i in range(2):
        np.testing.assert_allclose(cov[i, :s, :s], post, rtol=1e-8, atol=1e-12 * post.max())
    assert cov[0, 0, 0] < sigma ** 2


def test_covariance_stays_symmetric_positive_definite():
    """A tiny measurement noise (1e-6 m) against a large process noise and gaps up to 1 s
    (a condition number up to ~1e12): the Joseph form keeps ``P`` symmetric and positive
    definite."""
    rng = np.random.default_rng(11)
    est = ObstacleEstimator(4, 1e-6, process_std=1.0, model="constant-acceleration")
    t = 0.0
    for _ in range(300):
        t += rng.choice([1e-4, 1e-2, 1.0])
        est.update(rng.normal(0, 1, (4, 3)), t)
        cov = est.predict(t + rng.uniform(0, 0.05))[3]
        assert np.array_equal(cov, cov.transpose(0, 2, 1))
        assert np.all(np.linalg.eigvalsh(cov) > 0)


# ----------------------------------------------------------------------------- bookkeeping


def _estimator(o=2, **kw):
    kw = {"measurement_std": 0.01, "process_std": 0.3, **kw}
    return ObstacleEstimator(o, **kw)


def test_nan_rows_are_skipped():
    est = _estimator(3)
    z = np.arange(9.0).reshape(3, 3)
    z[1] = np.nan
    est.update(z, 0.0)
    assert not est.initialized
    assert est.last_sample_time[1] == -np.inf
    with pytest.raises(RuntimeError, match=r"\[1\]"):
        est.predict(0.1)
    partial = z + 0.01
    partial[1] = [1.0, np.nan, 2.0]                     # any NaN: no measurement
    est.update(partial, 0.05)
    assert not est.initialized
    z2 = z + 0.02
    z2[1] = [5.0, 6.0, 7.0]
    est.update(z2, 0.1)
    assert est.initialized
    # obstacle 1 starts at its first sample; 0 and 2 fused three
    p, v, _, cov = est.predict(0.1)
    np.testing.assert_array_equal(p[1], [5.0, 6.0, 7.0])
    np.testing.assert_array_equal(v[1], 0.0)
    assert cov[1, 0, 0] == pytest.approx(0.01 ** 2)
    assert cov[1, 1, 1] > cov[0, 1, 1]
    alone = _estimator(1)
    for zz, t in ((z, 0.0), (partial, 0.05), (z2, 0.1)):
        alone.update(zz[[0]], t)
    np.testing.assert_array_equal(alone.predict(0.1)[0][0], p[0])


def test_stale_and_repeated_samples_are_ignored():
    est = _estimator(2)
    est.update(np.zeros((2, 3)), 0.0)
    est.update(np.full((2, 3), 0.01), 0.1)
    before = est.predict(0.2)
    est.update(np.full((2, 3), 5.0), 0.1)               # the same sample time again
    est.update(np.full((2, 3), 5.0), 0.05)              # out of order
    est.update(np.full((2, 3), 5.0), np.array([0.1, -1.0]))
    after = est.predict(0.2)
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a, b)
    # per-obstacle times: only obstacle 1's newer sample is fused
    est.update(np.full((2, 3), 0.02), np.array([0.1, 0.15]))
    np.testing.assert_array_equal(est.last_sample_time, [0.1, 0.15])
    p, *_ = est.predict(0.2)
    np.testing.assert_array_equal(p[0], before[0][0])
    assert not np.array_equal(p[1], before[0][1])


def test_predict_before_any_measurement_raises():
    est = _estimator(2)
    with pytest.raises(RuntimeError, match="update"):
        est.predict(0.0)
    est.update(np.zeros((2, 3)), 0.0)
    est.predict(0.0)
    est.reset()
    assert not est.initialized
    with pytest.raises(RuntimeError):
        est.predict(1.0)


def test_predict_to_an_earlier_time_raises_naming_t():
    est = _estimator(2)
    est.update(np.zeros((2, 3)), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match=r"^t must"):
        est.predict(1.5)                                # before obstacle 1's sample
    with pytest.raises(ValueError, match=r"^t must"):
        est.predict(np.array([2.0, 1.99]))
    with pytest.raises(ValueError, match=r"^t must"):
        est.predict(np.nan)
    with pytest.raises(ValueError, match=r"^t must"):
        est.predict(np.array([3.0, 3.0, 3.0]))
    p, *_ = est.predict(np.array([1.0, 2.0]))           # each at its own sample time
    np.testing.assert_array_equal(p, 0.0)
    est.predict(2.0 - 1e-12)                            # rounding, not an earlier time


@pytest.mark.parametrize("kwargs, name", [
    ({"n_obstacles": 0}, "n_obstacles"),
    ({"n_obstacles": -2}, "n_obstacles"),
    ({"n_obstacles": 1.5}, "n_obstacles"),
    ({"n_obstacles": True}, "n_obstacles"),
    ({"n_obstacles": "3"}, "n_obstacles"),
    ({"measurement_std": 0.0}, "measurement_std"),
    ({"measurement_std": -0.01}, "measurement_std"),
    ({"measurement_std": np.nan}, "measurement_std"),
    ({"measurement_std": np.inf}, "measurement_std"),
    ({"measurement_std": "x"}, "measurement_std"),
    ({"process_std": 0.0}, "process_std"),
    ({"process_std": np.inf}, "process_std"),
    ({"process_std": None}, "process_std"),
    ({"model": "cv"}, "model"),
    ({"model": "constant-jerk"}, "model"),
    ({"initial_velocity_std": 0.0}, "initial_velocity_std"),
    ({"initial_velocity_std": np.nan}, "initial_velocity_std"),
    ({"initial_acceleration_std": -1.0}, "initial_acceleration_std"),
    ({"initial_acceleration_std": np.inf}, "initial_acceleration_std"),
])
def test_constructor_rejects_bad_arguments(kwargs, name):
    args = {"n_obstacles": 2, "measurement_std": 0.01, **kwargs}
    with pytest.raises(ValueError, match=f"^{name} "):
        ObstacleEstimator(**args)


def test_constructor_accepts_a_tiny_measurement_std():
    est = ObstacleEstimator(np.int64(1), 1e-12)
    est.update(np.ones((1, 3)), 0.0)
    est.update(np.ones((1, 3)), 0.01)
    assert est.predict(0.01)[3][0, 0, 0] <= 1e-24


@pytest.mark.parametrize("positions, sample_time, name", [
    (np.zeros((2, 2)), 0.0, "positions"),
    (np.zeros(3), 0.0, "positions"),
    (np.array([[0.0, 0.0, np.inf], [0.0, 0.0, 0.0]]), 0.0, "positions"),
    (np.zeros((2, 3)), np.zeros(3), "sample_time"),
    (np.zeros((2, 3)), np.array([0.0, np.nan]), "sample_time"),
    (np.zeros((2, 3)), np.inf, "sample_time"),
])
def test_update_rejects_bad_input(positions, sample_time, name):
    est = _estimator(2)
    with pytest.raises(ValueError, match=f"^{name} "):
        est.update(positions, sample_time)
    assert np.all(np.isinf(est.last_sample_time))


def test_nan_sample_time_of_a_missing_row_is_fine():
    est = _estimator(2)
    est.update(np.array([[0.0, 0.0, 0.0], [np.nan] * 3]), np.array([0.0, np.nan]))
    np.testing.assert_array_equal(est.last_sample_time, [0.0, -np.inf])


@pytest.mark.parametrize("model", ESTIMATOR_MODELS)
def test_predict_does_not_change_the_filter(model):
    rng = np.random.default_rng(9)
    a, b = _estimator(3, model=model), _estimator(3, model=model)
    for k in range(5):
        z = rng.normal(0, 1, (3, 3))
        a.update(z, 0.1 * k)
        b.update(z, 0.1 * k)
    first = a.predict(0.47)
    first[0][:] = 99.0                                  # the outputs are the caller's
    first[3][:] = 99.0
    again = a.predict(0.47)
    a.predict(np.array([0.45, 0.6, 2.0]))
    for x, y in zip(again, b.predict(0.47), strict=True):
        np.testing.assert_array_equal(x, y)
    z = rng.normal(0, 1, (3, 3))
    a.update(z, 0.5)
    b.update(z, 0.5)
    for x, y in zip(a.predict(0.55), b.predict(0.55), strict=True):
        np.testing.assert_array_equal(x, y)
