"""The learners' core's own exp (afvsgp_gym.gp._bank.vexp) against a 120-bit reference
(mpmath), at its range reduction's boundaries, across the subnormal and overflow edges and
at the special values, in every copy of the hot loops this CPU runs."""

import mpmath
import numpy as np
import pytest

from afvsgp_gym.gp import afvsgp_bank

core = afvsgp_bank._core
pytestmark = pytest.mark.skipif(core is None, reason="compiled core not built")
LN2 = float(np.log(2.0))


def _points() -> np.ndarray:
    """Random points where the learners' exponents lie ([-40, 2]) and over the whole finite
    range, the reduction's boundaries (k ln2 and (k + 1/2) ln2, where k = rint(x / ln2)
    changes) with their neighbours, and the subnormal and overflow thresholds."""
    rng = np.random.default_rng(0)
    edges = np.concatenate([LN2 * np.arange(-1074, 1024), LN2 * (np.arange(-1075, 1024) + 0.5)])
    edges = np.concatenate([edges, np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf)])
    return np.concatenate([
        rng.uniform(-40.0, 2.0, 4000), rng.uniform(-745.5, 709.9, 4000),
        rng.uniform(-0.35, 0.35, 1000), edges[rng.permutation(edges.size)[:3000]],
        [-708.0, np.nextafter(-708.0, -1.0), 709.0, np.nextafter(709.0, 710.0), 709.78,
         709.7827, -745.13, -745.14, -746.0, 710.0, -1e-300, 1e-300, 5e-324]])


def _ulp_errors(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """|y - exp(x)| in units of the last place of the correctly rounded exp(x) (120 bits);
    a result that should be 0 or inf must be exactly that."""
    mpmath.mp.prec = 120
    out = np.empty(x.size)
    for i, (xi, yi) in enumerate(zip(x, y, strict=True)):
        ref = mpmath.exp(mpmath.mpf(float(xi)))
        r = float(ref)
        if r == 0.0 or np.isinf(r):
            out[i] = 0.0 if yi == r else np.inf
        else:
            out[i] = float(abs(mpmath.mpf(float(yi)) - ref) / np.spacing(r))
    return out


@pytest.mark.parametrize("name", core.simd()[1] if core is not None else [])
def test_vexp_is_within_one_and_a_half_ulps_of_the_exact_exp(name, restore_simd):
    """In every copy: at most 1.5 ulp from exp(x) to 120 bits (the error analysis: the final
    addition 1 + q rounds by half an ulp, q = r + r^2 P(r) carries at most ~0.5 ulp of the
    result from its own roundings, doubled for results below 1, the reduction and the Taylor
    truncation far less; the subnormal results round once more in ldexp), exact at the special
    values, and the same digits in every copy."""
    core.simd(name)
    x = _points()
    y = x.copy()
    core.vexp(y)
    err = _ulp_errors(y, x)
    assert err.max() <= 1.5, (err.max(), x[err.argmax()])
    core.simd(core.simd()[1][-1])
    y_base = x.copy()
    core.vexp(y_base)
    np.testing.assert_array_equal(y, y_base)
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, -1e308, 1e308])
    core.simd(name)
    core.vexp(special)
    np.testing.assert_array_equal(special, [1.0, 1.0, np.inf, 0.0, np.nan, 0.0, np.inf])


def test_vexp_handles_every_length_and_refuses_bad_arrays():
    """Lengths that leave a tail after the vectors, and a non-float64 or read-only array
    refused by name."""
    rng = np.random.default_rng(1)
    for n in range(0, 40):
        x = rng.uniform(-30.0, 1.0, n)
        y = x.copy()
        core.vexp(y)
        np.testing.assert_allclose(y, np.exp(x), rtol=4 * np.finfo(float).eps, atol=0)
    with pytest.raises(ValueError, match="x must be of dtype float64"):
        core.vexp(np.zeros(4, dtype=np.float32))
    ro = np.zeros(4)
    ro.flags.writeable = False
    with pytest.raises(ValueError, match="x must be a C-contiguous, writable array"):
        core.vexp(ro)
