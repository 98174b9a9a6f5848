"""High-order control barrier function chain with linear class-K functions (paper sec. II-A).

For a barrier ``h`` of relative degree ``r`` and linear class-K functions
``alpha_i(s) = a_i s`` the chain is ``psi_0 = h``, ``psi_i = psi_{i-1}' + a_i psi_{i-1}``.
Writing ``p_k(s) = prod_{i<=k} (s + a_i)`` with coefficients ``c^(k)`` (constant first),
``psi_k = sum_j c^(k)_j h^(j)``. The HOCBF condition (Definition 3, eq. 44) reads

    psi_r = h^(r) + S + alpha_r(psi_{r-1}) >= 0,
    S = sum_{j=0}^{r-2} c^(r-1)_j h^(j+1)      (the Lie derivatives of the alpha terms),

with ``h^(r) = lf + lg @ u``. Everything here is plain numpy on the ``BarrierTerms`` record.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from afvsgp_gym.types import BarrierSet, BarrierTerms


def _as_gains(gains: float | Sequence[float], relative_degree: int) -> np.ndarray:
    if not isinstance(relative_degree, (int, np.integer)) or relative_degree < 1:
        raise ValueError(f"relative_degree must be a positive integer. Got: {relative_degree!r}")
    a = np.atleast_1d(np.asarray(gains, dtype=np.float64))
    if a.ndim != 1 or a.size not in (1, relative_degree):
        raise ValueError(
            f"alpha must be a scalar or have length relative_degree={relative_degree}. "
            f"Got: {gains!r}"
        )
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"alpha gains must be finite and positive (class K). Got: {gains!r}")
    return np.broadcast_to(a, (relative_degree,)).copy()


class HOCBF:
    """Linear-gain HOCBF chain of relative degree ``r`` (paper Definition 3, eq. 44).

    Parameters
    ----------
    relative_degree : int
        ``r >= 1``.
    alpha : float or sequence of float
        Gains ``a_1..a_r`` of the linear class-K functions; a scalar is used for all.
    """

    def __init__(self, relative_degree: int = 2, alpha: float | Sequence[float] = 1.0):
        self.gains = _as_gains(alpha, relative_degree)
        self.relative_degree = int(relative_degree)
        # coefficients of prod_{i<=k} (s + a_i), constant first, for k = 0..r
        coeffs = [np.array([1.0])]
        for a in self.gains:
            c = coeffs[-1]
            coeffs.append(np.concatenate([a * c, [0.0]]) + np.concatenate([[0.0], c]))
        self._coeffs = coeffs

    def psi(self, derivatives: np.ndarray) -> np.ndarray:
        """``[psi_0, ..., psi_{r-1}]`` from ``[h, ..., h^(r-1)]``."""
        d = np.asarray(derivatives, dtype=np.float64)
        return np.array([self._coeffs[k] @ d[: k + 1] for k in range(self.relative_degree)])

    def s_term(self, derivatives: np.ndarray) -> float:
        """``S`` of Definition 3: ``psi_{r-1}' - h^(r)`` (no action dependence)."""
        d = np.asarray(derivatives, dtype=np.float64)
        c = self._coeffs[self.relative_degree - 1]
        return float(c[:-1] @ d[1:]) if self.relative_degree > 1 else 0.0

    def offset(self, derivatives: np.ndarray) -> float:
        """``S + alpha_r(psi_{r-1})``: the part of ``psi_r`` that is not ``h^(r)``."""
        d = np.asarray(derivatives, dtype=np.float64)
        c = self._coeffs[self.relative_degree]
        return float(c[:-1] @ d)

    def constraint(self, terms: BarrierTerms) -> tuple[float, np.ndarray]:
        """Affine nominal constraint ``c0 + c @ u >= 0`` of eq. 45: ``(lf + S + alpha, lg)``."""
        if terms.relative_degree != self.relative_degree:
            raise ValueError(
                f"terms.derivatives has length {terms.relative_degree}, expected the relative "
                f"degree {self.relative_degree}"
            )
        return float(terms.lf) + self.offset(terms.derivatives), np.asarray(
            terms.lg, dtype=np.float64
        )

    def constraints(self, terms: BarrierSet) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 45 for K barriers at once: ``c0`` (K,) and ``c`` (K, m), ``c0 + c @ u >= 0``."""
        if terms.relative_degree != self.relative_degree:
            raise ValueError(
                f"terms have relative degree {terms.relative_degree}, expected "
                f"{self.relative_degree}"
            )
        return terms.lf + terms.derivatives @ self._coeffs[self.relative_degree][:-1], terms.lg
