"""The (sphere, obstacle) pair geometry against an extended-precision reference."""

import numpy as np
import pytest

from afvsgp_gym.envs.scenario import pair_barriers, sphere_barriers

EPS = np.finfo(np.float64).eps


def _reference(d, v, radius):
    """h, h', n, curvature in long double from the definitions (eq. of the HOCBF terms)."""
    d, v = d.astype(np.longdouble), v.astype(np.longdouble)
    dist = np.sqrt((d * d).sum(axis=1))
    n = d / dist[:, None]
    ndv = (n * v).sum(axis=1)
    curv = ((v * v).sum(axis=1) - ndv * ndv) / dist
    return dist - radius, ndv, n, curv


@pytest.mark.parametrize("dim", [2, 3])
def test_pair_geometry_equals_reference_to_rounding(dim):
    """Each output within a few ulps of its conditioning: |h| + |d| + r for h, |v| for h',
    1 for n, |v|^2 / |d| for the curvature (cancellation when v is parallel to d)."""
    rng = np.random.default_rng(0)
    k = 400
    d = rng.normal(size=(k, dim)) * rng.uniform(1e-3, 2.0, (k, 1))
    v = rng.normal(size=(k, dim)) * rng.uniform(1e-3, 3.0, (k, 1))
    v[:50] = d[:50] * rng.uniform(-2, 2, (50, 1)) + 1e-9 * v[:50]  # nearly parallel
    radius = rng.uniform(0.02, 0.2, k)
    h, hd, n, curv = sphere_barriers(d, v, radius)
    rh, rhd, rn, rcurv = _reference(d, v, radius)
    dist = np.linalg.norm(d, axis=1)
    vn = np.linalg.norm(v, axis=1)
    tol = 8 * EPS
    assert np.all(np.abs(h - rh) <= tol * (dist + radius))
    assert np.all(np.abs(hd - rhd) <= tol * vn)
    assert np.all(np.abs(n - rn) <= tol)
    assert np.all(np.abs(curv - rcurv) <= 2 * tol * vn * vn / dist)
    hh, n2, curv2 = pair_barriers(np.stack((d, v), axis=1), radius)
    np.testing.assert_array_equal(hh, np.stack((h, hd), axis=1))
    np.testing.assert_array_equal(n2, n)
    np.testing.assert_array_equal(curv2, curv)


def test_pair_geometry_clamps_the_distance():
    h, hd, n, curv = sphere_barriers(np.zeros((1, 3)), np.ones((1, 3)), np.array([0.1]))
    assert h[0] == 1e-9 - 0.1
    assert np.all(np.isfinite(n)) and np.isfinite(hd[0]) and np.isfinite(curv[0])
