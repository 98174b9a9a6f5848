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


def braking_alpha(h: np.ndarray, gain: float | np.ndarray,
                  deceleration: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first class-K function of a relative-degree-2 barrier that respects a bounded
    deceleration, and its derivative: ``(alpha_1(h), alpha_1'(h))``.

    ``alpha_1(h) = 2 a h / (1 + s)``, ``alpha_1'(h) = a / s``, ``s = sqrt(1 + 2 a^2 |h| / A)``
    (odd in h), ``a`` the gain, ``A`` the deceleration. It is ``sqrt(2 A h + c^2) - c`` with
    ``c = A / a`` (rationalised: no cancellation), so ``psi_1 = h' + alpha_1(h) >= 0`` bounds the
    approach speed by the braking curve of deceleration ``A``, offset so that the slope at the
    boundary is ``a``; ``A = inf`` gives the linear ``a h`` (and ``a``) exactly.
    ``alpha_1 alpha_1' < A`` everywhere, which is what makes ``psi_2 >= 0`` satisfiable
    whenever ``h''`` can reach ``A`` (:class:`BarrierConstraints`).
    """
    s = np.sqrt(1.0 + (2.0 * gain * gain) * np.abs(h) / deceleration)
    return (2.0 * gain) * h / (1.0 + s), gain / s


class BarrierConstraints:
    """The HOCBF constraints (eq. 45) of K barriers with their own relative degrees and,
    for relative degree 2, a braking class-K function.

    Barrier ``k`` of relative degree ``r_k`` uses the gains ``a_1..a_{r_k}`` (the first
    ``r_k`` of ``alpha``), its first one replaced by ``first_gain[k]`` when given. Relative
    degree 1: ``psi_1 = h' + a_1 h``. Relative degree 2 with
    deceleration ``A_k`` (``inf``: the linear chain):

        psi_1 = h' + alpha_1(h),   psi_2 = h'' + alpha_1'(h) h' + a_2 psi_1 >= 0,

    with ``alpha_1`` of :func:`braking_alpha`. Where ``psi_1 = 0`` the constraint asks for
    ``h'' >= alpha_1 alpha_1' < A_k``, and inside (``psi_1 > 0``) for less: if the actions can
    make ``h'' >= A_k`` at every state with ``psi_1 >= 0``, the program of this barrier alone
    is feasible there (the torque limits' stopping distance, Agrawal and Panagou 2021's
    input-constrained CBFs). Higher degrees use the linear chain (no braking form).

    Parameters
    ----------
    relative_degree : array_like of int, shape (K,)
    alpha : float or sequence of float
        ``a_1..a_r`` for the largest degree ``r`` (a scalar for all).
    deceleration : array_like of float, shape (K,)
        ``A_k > 0`` in units of ``h`` per s^2; ``inf`` for the linear chain.
    activation : array_like of float, shape (K,)
        ``D_k >= 0`` (units of ``h``, ``inf``: always): see :meth:`active_rows`.
    first_gain : array_like of float, shape (K,), or None
        ``a_1`` per barrier of relative degree 1 or 2 (NaN or None: ``alpha``'s).
    """

    def __init__(self, relative_degree, alpha, deceleration, activation=np.inf,
                 first_gain=None):
        deg = np.asarray(relative_degree, dtype=np.int64)
        self.degrees = deg
        self.chain = HOCBF(int(deg.max()), alpha)
        self.gains = self.chain.gains
        decel = np.broadcast_to(np.asarray(deceleration, dtype=np.float64), deg.shape).copy()
        if np.any(~(decel > 0)):
            raise ValueError(f"deceleration must be > 0 (inf: linear). Got: {decel}")
        if np.any(np.isfinite(decel) & (deg != 2)):
            raise ValueError("a finite deceleration needs relative degree 2")
        self.deceleration = decel
        first = np.full(deg.shape, self.gains[0])
        if first_gain is not None:
            given = np.broadcast_to(np.asarray(first_gain, dtype=np.float64), deg.shape)
            first = np.where(np.isnan(given), first, given)
        if np.any(~(first > 0)) or np.any(np.isinf(first)):
            raise ValueError(f"first_gain must be finite and > 0. Got: {first}")
        if np.any((first != self.gains[0]) & (deg > 2)):
            raise ValueError("first_gain applies to relative degrees 1 and 2 only")
        self.first_gain = first
        act = np.broadcast_to(np.asarray(activation, dtype=np.float64), deg.shape).copy()
        if np.any(~(act >= 0)):
            raise ValueError(f"activation must be >= 0 (inf: always). Got: {act}")
        self.activation = act
        self.uniform_linear = bool(np.all(deg == deg[0]) and np.all(np.isinf(decel))
                                   and np.all(first == self.gains[0]))
        self._by_degree = [(int(r), np.flatnonzero(deg == r),
                            HOCBF(int(r), self.gains[:r])._coeffs[r][:-1]) for r in np.unique(deg)]
        self._braking = np.flatnonzero(np.isfinite(decel))
        self._two = two = np.flatnonzero(deg == 2)
        with np.errstate(invalid="ignore"):  # D = inf: every such barrier is active anyway
            self._alpha_at_activation = braking_alpha(act[two], first[two], decel[two])[0]
        self._cache: tuple | None = None
        #: d psi_r / d h at h = 0 per barrier: the product of its gains
        self.margin_gain = first * np.array([np.prod(self.gains[1:r]) for r in deg])

    def _first(self, derivatives: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``alpha_1(h)`` and ``alpha_1'(h)`` of the relative-degree-2 barriers, computed once
        per state: a read-only derivatives array (an env's, shared by the constraints, the
        activation and the ground truth of one step) is remembered until the next one."""
        cached = self._cache
        if cached is not None and cached[0] is derivatives:
            return cached[1]
        two = self._two
        out = braking_alpha(derivatives[two, 0], self.first_gain[two], self.deceleration[two])
        if not derivatives.flags.writeable:
            self._cache = (derivatives, out)
        return out

    def psi1(self, derivatives: np.ndarray) -> np.ndarray:
        """``psi_1`` (K,) of every barrier (``h`` itself for relative degree 1: its psi_1
        involves the action)."""
        d = derivatives
        out = d[:, 0].copy()
        two = self._two
        if len(two):
            out[two] = d[two, 1] + self._first(d)[0]
        return out

    def constraints(self, terms: BarrierSet) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 45 of every barrier: ``c0`` (K,) and ``c`` (K, m), ``c0 + c @ u >= 0``."""
        if self.uniform_linear:
            return self.chain.constraints(terms)
        d = terms.derivatives
        if d.shape[1] != self.chain.relative_degree:
            raise ValueError(f"terms have {d.shape[1]} derivative columns, expected "
                             f"{self.chain.relative_degree}")
        c0 = np.array(terms.lf, dtype=np.float64)
        first = self.first_gain
        for r, rows, coeffs in self._by_degree:
            if r == 1:
                c0[rows] += first[rows] * d[rows, 0]
            elif r == 2:  # rows is self._two
                hd = d[rows, 1]
                alpha, slope = self._first(d)
                c0[rows] += slope * hd + self.gains[1] * (hd + alpha)
            else:
                c0[rows] += d[rows, :r] @ coeffs
        return c0, terms.lg

    def active_rows(self, derivatives: np.ndarray) -> np.ndarray:
        """Barriers within their ``activation`` distance ``D`` of the boundary: ``h < D`` or,
        relative degree >= 2, ``psi_1 < alpha_1(D)`` (approaching fast enough to reach ``D`` by
        the class-K rate); outside both, ``h >= D`` and ``psi_1 >= alpha_1(D) > 0``, so a barrier
        enters the program with its first HOCBF condition holding with margin. NaN terms are
        not active (the caller adds them)."""
        h = derivatives[:, 0]
        near = h < self.activation
        two = self._two
        if len(two):
            near[two] |= derivatives[two, 1] + self._first(derivatives)[0] < \
                self._alpha_at_activation
        return np.flatnonzero(near)
