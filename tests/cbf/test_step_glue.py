"""The controller's compiled glue (afvsgp_gym.cbf._step): the eq. 48 samples and the residual
observer give the numpy versions' digits on random and edge-case data; bad input is refused
naming the argument and the wrappers then run numpy. Through the controller (the barriers in
the program, the learned terms and cone matrices): tests/cbf/test_backends.py."""

import numpy as np
import pytest

from afvsgp_gym.cbf import controller
from afvsgp_gym.cbf.measurement import measure_samples
from afvsgp_gym.cbf.residuals import ResidualObserver
from afvsgp_gym.types import BarrierSet

needs_core = pytest.mark.skipif(controller._step is None, reason="_step not built")
M = 7


def _barriers(rng, K, r=2, b=20):
    return BarrierSet(rng.normal(size=(K, r)), rng.normal(size=K), rng.normal(size=(K, M)),
                      rng.normal(size=(K, b)))


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
def test_bad_input_to_the_glue_is_refused_and_the_wrappers_run_numpy():
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
    want = measure_samples(before, u, single, 0.01, backend="numpy")
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    obs = ResidualObserver(K, 0.5)
    obs.update(np.array([1, 1]), np.zeros(2), z=np.ones(K))  # duplicates: numpy's semantics
    assert obs.bias[1] == 0.5 and not obs.bias[[0, 2, 3, 4]].any()
