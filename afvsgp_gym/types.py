"""Plain data shared by the environments and the safety filter (numpy only, no simulator)."""

from __future__ import annotations

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
