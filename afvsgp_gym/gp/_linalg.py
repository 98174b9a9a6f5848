"""Shared numerics for the GP learners: the jitter policy, jittered Cholesky and the array
checks (``check_matrix``, ``check_batch``, ``check_sample``; the scalar checks ``check_count``,
``check_real`` are the package's, from :mod:`afvsgp_gym.validation`), each raising
``ValueError`` naming the argument.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.linalg import LinAlgError, cholesky

from afvsgp_gym.validation import check_count, check_real  # the package's scalar checks

__all__ = [
    "DEFAULT_JITTER",
    "jitter_for",
    "check_batch",
    "check_count",
    "check_real",
    "check_matrix",
    "check_sample",
    "jittered_cholesky",
    "ubar",
]

#: Relative jitter of the sparse learners (see :func:`jitter_for`).
DEFAULT_JITTER = 1e-8


def jitter_for(koo: np.ndarray, relative: float) -> float:
    """The jitter policy of every sparse learner: ``relative * mean(diag K_oo)`` is added to the
    diagonal of ``K_oo`` (the inducing variables are ``f(o) + e``, ``var(e)`` that value).

    Relative to the inducing prior variances, so it bounds ``cond(K_oo)`` by about
    ``M / relative`` whatever the kernel's scale. The learners fix it when they set up an
    inducing set (``jitter_``); the hyperparameter fit lets it follow the kernel.
    """
    return float(relative) * float(np.mean(np.diag(koo))) if koo.size else 0.0


def jittered_cholesky(a: np.ndarray, *, jitter: float = 0.0, max_tries: int = 10,
                      name: str = "matrix") -> np.ndarray:
    """Lower Cholesky factor of ``a + jitter I``.

    If the factorisation fails, retries with jitter growing tenfold from
    ``max(jitter, 1e-10 * mean |diag a|)`` and warns (``RuntimeWarning``) with the jitter
    that worked. Raises ``LinAlgError`` after ``max_tries`` failures or on non-finite input.
    """
    a = np.asarray(a, dtype=np.float64)
    n = a.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    if not np.all(np.isfinite(a)):
        raise LinAlgError(f"{name} has non-finite entries")
    eye = np.eye(n)
    try:
        return cholesky(a + jitter * eye if jitter else a, lower=True, check_finite=False)
    except LinAlgError:
        pass
    scale = float(np.mean(np.abs(np.diag(a)))) or 1.0
    extra = max(jitter, 1e-10 * scale)
    for _ in range(max_tries):
        try:
            low = cholesky(a + extra * eye, lower=True, check_finite=False)
        except LinAlgError:
            extra *= 10.0
            continue
        warnings.warn(f"Cholesky of {name} needed jitter {extra:.3g} (diagonal scale "
                      f"{scale:.3g}); the matrix is close to singular", RuntimeWarning,
                      stacklevel=2)
        return low
    raise LinAlgError(f"Cholesky of {name} failed even with jitter {extra:.3g}; "
                      "check the kernel hyperparameters and inputs")


def ubar(u: np.ndarray) -> np.ndarray:
    """``[1, u]`` row-wise: (N, m) -> (N, m+1) (the 1 first, paper eq. 19)."""
    out = np.empty((u.shape[0], u.shape[1] + 1))
    out[:, 0] = 1.0
    out[:, 1:] = u
    return out


def check_matrix(x, name: str, *, ncols: int | None = None, nrows: int | None = None,
                 ndim: int = 2) -> np.ndarray:
    """float64 copy of ``x`` with ``ndim`` dims, finite; ``ValueError`` naming ``name``."""
    try:
        arr = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array: {exc}") from None
    if arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    if ndim == 2 and ncols is not None and arr.shape[1] != ncols:
        raise ValueError(f"{name} must have {ncols} columns, got shape {arr.shape}")
    if nrows is not None and arr.shape[0] != nrows:
        raise ValueError(f"{name} must have {nrows} rows, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def check_batch(xi, u, z=None, *, input_dim: int | None = None,
                action_dim: int | None = None):
    """Validate a batch: xi (N, b), u (N, m), z (N,) -> float64 copies (z None passes)."""
    xi = check_matrix(xi, "xi", ncols=input_dim)
    n = xi.shape[0]
    if n == 0:
        raise ValueError("xi must contain at least one row")
    u = check_matrix(u, "u", ncols=action_dim, nrows=n)
    if z is not None:
        z = check_matrix(z, "z", ndim=1, nrows=n)
    return xi, u, z


def check_sample(xi, u, z, *, input_dim: int, action_dim: int):
    """Validate one sample: xi (b,), u (m,), z scalar -> (xi, u, float(z))."""
    xi = check_matrix(xi, "xi", ndim=1, nrows=input_dim)
    u = check_matrix(u, "u", ndim=1, nrows=action_dim)
    z = check_matrix(z, "z", ndim=0)
    return xi, u, float(z)


