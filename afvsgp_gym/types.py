"""Plain data shared by the environments and the safety filter (numpy only, no simulator)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BarrierTerms:
    """Known parts of one barrier's derivatives at the current state.

    For a barrier h of relative degree ``r`` with respect to the action ``u`` (as passed to
    ``env.step``), ``h^(r) = lf + lg @ u`` (paper eq. 44 with F = [lf, lg]).

    Attributes
    ----------
    derivatives : ndarray of shape (r,)
        ``[h, h', ..., h^(r-1)]``, measurable from the state.
    lf : float
        The part of ``h^(r)`` that does not depend on the action (L_f^r h).
    lg : ndarray of shape (action_dim,)
        ``d h^(r) / d u`` (L_g L_f^(r-1) h).
    xi : ndarray of shape (feature_dim,)
        The GP feature vector for this barrier (documented by each environment).
    """

    derivatives: np.ndarray
    lf: float
    lg: np.ndarray
    xi: np.ndarray

    @property
    def relative_degree(self) -> int:
        return int(np.shape(self.derivatives)[0])

    @property
    def h(self) -> float:
        return float(self.derivatives[0])


@dataclass(frozen=True)
class BarrierSet(Sequence):
    """The terms of ``K`` barriers in stacked float64 arrays; a sequence of :class:`BarrierTerms`.

    Environments return one per model and state; the safety controller reads the arrays
    directly (no per-barrier objects in the control loop). ``BarrierSet.stack(terms)`` builds
    one from a list of :class:`BarrierTerms`.

    Attributes
    ----------
    derivatives : ndarray of shape (K, r)
    lf : ndarray of shape (K,)
    lg : ndarray of shape (K, action_dim)
    xi : ndarray of shape (K, feature_dim)
    """

    derivatives: np.ndarray
    lf: np.ndarray
    lg: np.ndarray
    xi: np.ndarray

    @classmethod
    def stack(cls, terms: Sequence[BarrierTerms]) -> BarrierSet:
        """Stack a sequence of :class:`BarrierTerms` (or return a ``BarrierSet`` as it is).

        Raises ``ValueError`` when the terms have inconsistent shapes."""
        if isinstance(terms, BarrierSet):
            return terms
        terms = list(terms)
        if not terms:
            raise ValueError("terms must hold at least one BarrierTerms")
        try:
            return cls(
                np.array([t.derivatives for t in terms], dtype=np.float64),
                np.array([t.lf for t in terms], dtype=np.float64),
                np.array([t.lg for t in terms], dtype=np.float64),
                np.array([t.xi for t in terms], dtype=np.float64),
            )
        except (AttributeError, TypeError, ValueError) as exc:
            raise ValueError(
                f"terms must be BarrierTerms with equal shapes across barriers: {exc}"
            ) from None

    def __len__(self) -> int:
        return int(self.lf.shape[0])

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        return BarrierTerms(self.derivatives[k], float(self.lf[k]), self.lg[k], self.xi[k])

    def __iter__(self) -> Iterator[BarrierTerms]:
        return (self[k] for k in range(len(self)))

    @property
    def relative_degree(self) -> int:
        return int(self.derivatives.shape[1])

    @property
    def h(self) -> np.ndarray:
        """``(K,)`` barrier values."""
        return self.derivatives[:, 0]
