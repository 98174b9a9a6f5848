"""The controller's compiled glue (afvsgp_gym.cbf._step: the barriers in the program, the
learned terms and cone matrices, the eq. 48 samples, the residual observer) gives the numpy
versions' digits: entry by entry on random and edge-case data, and over a whole-arm closed
loop step by step; bad input is refused naming the argument and the wrappers then run numpy."""

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401  (registers the envs)
from afvsgp_gym.agents import NominalController
from afvsgp_gym.cbf import SafetyController, controller, measurement, residuals
from afvsgp_gym.cbf.controller import cone_matrices
from afvsgp_gym.cbf.measurement import measure_samples
from afvsgp_gym.cbf.residuals import ResidualObserver
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.wrappers import SafetyFilter

needs_core = pytest.mark.skipif(controller._step is None, reason="_step not built")
M = 7


def _barriers(rng, K, r=2, b=20):
    return BarrierSet(rng.normal(size=(K, r)), rng.normal(size=K), rng.normal(size=(K, M)),
                      rng.normal(size=(K, b)))


def _controller(K, **kw):
    return SafetyController(-np.ones(M), np.ones(M), n_barriers=K, learner="none", **kw)


@needs_core
@pytest.mark.parametrize("r", [1, 2, 3])
def test_active_rows_are_the_numpy_rows(r):
    """The same rows as the numpy version, ties at the activation distance and signed zeros
    included; -1 (rows untouched) when a term is not finite, and the controller then flags
    those rows as the numpy path does."""
    rng = np.random.default_rng(r)
    K = 40
    ctrl = _controller(K, activation_distance=0.1, relative_degree=r)
    bset = _barriers(rng, K, r)
    d = bset.derivatives
    d[:5, 0] = [0.1, -0.0, 0.0, 0.1 - 1e-17, np.nextafter(0.1, 1.0)]
    if r > 1:
        d[5, :2] = [0.2, (0.1 - 0.2) * ctrl.hocbf.gains[0]]  # h + h'/a_1 at the distance
    c0, c = ctrl.hocbf.constraints(bset)
    got = ctrl._finite_active_rows(c0, c, bset)
    np.testing.assert_array_equal(got, ctrl._active_rows(d, None))
    assert got.dtype == np.int64 and 0 < len(got) < K
    for name in ("derivatives", "xi", "lg"):
        bad = BarrierSet(*(getattr(bset, f).copy() for f in ("derivatives", "lf", "lg", "xi")))
        getattr(bad, name)[7, 0] = np.nan
        c0, c = ctrl.hocbf.constraints(bad)
        assert ctrl._finite_active_rows(c0, c, bad) is None
        res = ctrl.filter(np.zeros(M), bad)
        assert res.status.startswith("fallback") or 7 not in np.flatnonzero(
            np.isfinite(res.margins))


@needs_core
def test_learned_terms_are_the_numpy_terms():
    """a0 += bvec[:, 0] + bias[rows], a += bvec[:, 1:] and the cone matrices, digit for digit;
    a covariance that is not positive definite gets the eigen-factor of the numpy path."""
    rng = np.random.default_rng(5)
    K, n, c = 21, 6, M + 1
    ctrl = _controller(K, beta=1.3)
    ctrl.residuals.bias[:] = rng.normal(size=K)
    rows = np.sort(rng.choice(K, n, replace=False)).astype(np.int64)
    a0, a, bvec = rng.normal(size=n), rng.normal(size=(n, M)), rng.normal(size=(n, c))
    q = rng.normal(size=(n, c, c))
    sig = q @ q.transpose(0, 2, 1) + 1e-3 * np.eye(c)
    sig[2] -= 2.0 * np.linalg.eigvalsh(sig[2]).max() * np.eye(c)  # negative definite
    want_a0 = a0 + (bvec[:, 0] + ctrl.residuals.bias[rows])
    want_a = a + bvec[:, 1:]
    done, G = ctrl._learned_terms(a0, a, bvec, rows, sig)
    assert done
    np.testing.assert_array_equal(a0, want_a0)
    np.testing.assert_array_equal(a, want_a)
    np.testing.assert_array_equal(G, cone_matrices(sig, 1.3))
    ctrl.config = ctrl.config.__class__(beta=0.0)
    done, G = ctrl._learned_terms(a0, a, bvec, rows, sig)
    assert done and G is None
    np.testing.assert_array_equal(a0, want_a0 + (bvec[:, 0] + ctrl.residuals.bias[rows]))


@needs_core
def test_measure_samples_are_eq_48():
    """z = (h'_after - h'_before) / dt - ((lf + lg u)_before + (lf + lg u)_after) / 2 and the
    midpoint features, as written here; the count of samples with a non-finite z or xi."""
    rng = np.random.default_rng(6)
    before, after = _barriers(rng, 21), _barriers(rng, 21)
    u, dt = rng.normal(size=M), 0.002
    xi, z, bad = measure_samples(before, u, after, dt)
    fd = (after.derivatives[:, 1] - before.derivatives[:, 1]) / dt
    nominal = 0.5 * ((before.lf + before.lg @ u) + (after.lf + after.lg @ u))
    np.testing.assert_array_equal(z, fd - nominal)
    np.testing.assert_array_equal(xi, 0.5 * (before.xi + after.xi))
    assert bad == 0
    after.xi[3, 4], before.lf[8], after.derivatives[8, 1] = np.inf, np.nan, np.nan
    xi, z, bad = measure_samples(before, u, after, dt)
    assert bad == 2 and np.isnan(z[8]) and np.isinf(xi[3, 4]) and np.isfinite(z[3])
    with pytest.raises(ValueError, match="dt"):
        measure_samples(before, u, after, -1.0)


@needs_core
@pytest.mark.parametrize("weight", [0.0, 0.3])
def test_residual_update_from_z_is_the_numpy_update(weight):
    """update(rows, predicted, z=z) equals update(rows, predicted, z[rows]) in numpy, NaN
    measurements and the reset of the barriers left out included."""
    rng = np.random.default_rng(7)
    K = 21
    z = rng.normal(size=K)
    z[[2, 9]] = np.nan
    rows = np.array([1, 2, 5, 9, 14], dtype=np.int64)
    pred = rng.normal(size=len(rows))
    fast, ref = ResidualObserver(K, weight), ResidualObserver(K, weight)
    fast.bias[:] = ref.bias[:] = rng.normal(size=K)
    fast.update(rows, pred, z=z)
    ref.update(rows, pred, z[rows])
    np.testing.assert_array_equal(fast.bias, ref.bias)


@needs_core
def test_bad_input_to_the_glue_is_refused_and_the_wrappers_run_numpy(monkeypatch):
    from afvsgp_gym.cbf import _step

    K = 5
    ok = dict(c0=np.zeros(K), c=np.zeros((K, M)), d=np.zeros((K, 2)), xi=np.zeros((K, 3)))
    with pytest.raises(ValueError, match="rows must be of dtype int64"):
        _step.active_rows(K, M, 2, 3, *ok.values(), 1.0, 0.1, np.zeros(K, np.int32))
    with pytest.raises(ValueError, match="derivatives must hold 10"):
        _step.active_rows(K, M, 2, 3, ok["c0"], ok["c"], np.zeros((K, 3)), ok["xi"], 1.0, 0.1,
                          np.zeros(K, np.int64))
    with pytest.raises(ValueError, match="rows must lie in"):
        _step.learned_terms(1, M, K, np.zeros(1), np.zeros((1, M)), np.zeros((1, M + 1)),
                            np.zeros(K), np.array([K]), np.eye(M + 1)[None], 1.0,
                            np.zeros((1, M + 1, M + 1)))
    with pytest.raises(ValueError, match="G must be a C-contiguous, writable"):
        _step.learned_terms(1, M, K, np.zeros(1), np.zeros((1, M)), np.zeros((1, M + 1)),
                            np.zeros(K), np.array([0]), np.eye(M + 1)[None], 1.0, None)
    with pytest.raises(ValueError, match="rows must be distinct"):
        _step.residual_update(K, 2, np.zeros(K), np.array([1, 1]), np.zeros(2), np.zeros(K),
                              0.5)
    with pytest.raises(ValueError, match="z_out"):
        _step.measure(K, 2, 3, 0.1, *[np.zeros(K), np.zeros(K), np.zeros((K, 2)),
                                      np.zeros((K, 3))] * 2, np.zeros((K, 3)), np.zeros(K - 1))
    # float32 terms (a BarrierSet built by hand): the numpy versions, the same answers
    rng = np.random.default_rng(8)
    before, after = _barriers(rng, K), _barriers(rng, K)
    single = BarrierSet(*(getattr(after, f).astype(np.float32)
                          for f in ("derivatives", "lf", "lg", "xi")))
    u = rng.normal(size=M)
    got = measure_samples(before, u, single, 0.01)
    monkeypatch.setattr(measurement, "_step", None)
    want = measure_samples(before, u, single, 0.01)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    obs = ResidualObserver(K, 0.5)
    obs.update(np.array([1, 1]), np.zeros(2), z=np.ones(K))  # duplicates: numpy's semantics
    assert obs.bias[1] == 0.5 and not obs.bias[[0, 2, 3, 4]].any()


@needs_core
def test_whole_arm_loop_is_the_same_with_and_without_the_compiled_glue():
    """Two 21-barrier AFVSGP episodes advanced in lockstep, one on the compiled glue and one
    on the numpy versions: the same observations and filter results at every step, through
    the warm-up and past the obstacle's approach (the chaotic closed loop would amplify any
    difference)."""
    envs, policies, obs = [], [], []
    for _ in range(2):
        env = SafetyFilter(gym.make("afvsgp_gym/FrankaObstacleStatic-v0"), learner="afvsgp",
                           seed=0)
        envs.append(env)
        policies.append(NominalController(env))
        obs.append(env.reset(seed=0)[0])
    glue = controller._step
    ctrl = envs[1].controller
    ctrl._finite_active_rows = lambda c0, c, bset: None
    ctrl._learned_terms = lambda a0, a, bvec, rows, sig: (False, None)
    predicted = 0
    try:
        for _ in range(900):
            infos = []
            for i, env in enumerate(envs):
                for mod in (measurement, residuals):
                    mod._step = glue if i == 0 else None
                obs[i], _, _, _, info = env.step(policies[i](obs[i]))
                infos.append(info)
            np.testing.assert_array_equal(obs[0], obs[1])
            for key in ("cost", "h", "filter_status", "delta_b_mean", "delta_b_std"):
                nan = key != "filter_status"
                assert np.array_equal(infos[0][key], infos[1][key], equal_nan=nan)
            predicted += int(np.isfinite(infos[0]["delta_b_mean"]).any())
    finally:
        for mod in (measurement, residuals):
            mod._step = glue
    assert predicted > 100  # steps with barriers in the program, predicted
    np.testing.assert_array_equal(envs[0].controller.residuals.bias, ctrl.residuals.bias)
