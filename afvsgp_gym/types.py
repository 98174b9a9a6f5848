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
    covariance : ndarray of shape (K, r + 1, r + 1) or None
        Covariance of each barrier's measured ``[h, ..., h^(r-1), lf]`` from the sensing
        (an obstacle estimate, noisy encoders); None where they are exact. The filter turns it
        into a back-off of the constraint (:class:`~afvsgp_gym.cbf.SafetyController`).
    projection : ndarray of shape (K, L) or None
        For a :class:`BarrierLayout` with projected barriers (``learner[k] == -1``): barrier
        ``k``'s model error is ``projection[k] @ e`` of the ``L`` learners' quantities ``e``
        (e.g. ``n' J_s(q)`` onto the joint acceleration errors); rows of barriers with their
        own learner are not read. None where the model does not say (e.g. nothing known).
    """

    derivatives: np.ndarray
    lf: np.ndarray
    lg: np.ndarray
    xi: np.ndarray
    covariance: np.ndarray | None = None
    projection: np.ndarray | None = None

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


@dataclass(frozen=True)
class BarrierLayout:
    """What a filter needs to know about K barriers besides their terms: each one's relative
    degree, and which barriers share one model error.

    Barriers of relative degree ``r_k`` below the set's largest ``r`` keep their measured
    derivatives ``[h, ..., h^(r_k - 1)]`` in the first ``r_k`` columns of
    ``BarrierSet.derivatives`` (the rest is 0), and ``lf + lg u`` is their ``h^(r_k)``.

    ``learner[k]`` numbers the model error of barrier ``k``: barriers with the same number have
    ``Delta B_k = sign[k] Delta B`` of one quantity (e.g. the lower and upper range and speed
    barriers of one joint all see ``+-`` that joint's acceleration error), so one learner
    serves them all (whatever their relative degrees: a joint's range barrier, of degree 2,
    and its speed barrier, of degree 1, both learn ``h^(r)`` = +- the joint's acceleration).
    Learners are numbered in order of first appearance, and the first barrier
    of each learner (its representative) has sign +1. ``group[l]`` labels learner ``l``'s
    hyperparameter-sharing group (learners of different physical quantities do not share).

    ``learner[k] == -1`` marks a *projected* barrier, which has no learner of its own: its
    model error is a linear map of the learners' quantities, given per state by
    ``BarrierSet.projection`` (issue 45's shared learner: an obstacle pair's
    ``Delta h'' = n' J_s(q) Delta q''`` onto the joint-acceleration learners of the
    joint-limit barriers). Its sign is +1.

    Attributes
    ----------
    relative_degree : ndarray of int, shape (K,)
    learner : ndarray of int, shape (K,)
    sign : ndarray of float, shape (K,)
        +1 or -1.
    group : ndarray of int, shape (L,)
        ``L`` = number of learners.
    """

    relative_degree: np.ndarray
    learner: np.ndarray
    sign: np.ndarray
    group: np.ndarray

    def __post_init__(self) -> None:
        deg = np.asarray(self.relative_degree)
        K = deg.shape[0] if deg.ndim == 1 else 0
        if K == 0 or not np.issubdtype(deg.dtype, np.integer) or np.any(deg < 1):
            raise ValueError(f"relative_degree must be K >= 1 integers >= 1, got {deg!r}")
        lrn = np.asarray(self.learner)
        sign = np.asarray(self.sign, dtype=np.float64)
        if lrn.shape != (K,) or not np.issubdtype(lrn.dtype, np.integer):
            raise ValueError(f"learner must hold {K} integers, got {lrn!r}")
        if sign.shape != (K,) or not np.all(np.abs(sign) == 1.0):
            raise ValueError(f"sign must hold {K} values +1 or -1, got {sign!r}")
        own = np.flatnonzero(lrn >= 0)
        _, first = np.unique(lrn[own], return_index=True)
        first = own[first]
        L = len(first)
        if L == 0 or np.any(lrn < -1) or not np.array_equal(np.sort(first), first) or \
                not np.array_equal(lrn[np.sort(first)], np.arange(L)):
            raise ValueError("learner must number the learners 0, 1, ... in order of first "
                             f"appearance (-1: projected), got {lrn.tolist()}")
        if np.any(sign[first] != 1.0) or np.any(sign[lrn < 0] != 1.0):
            raise ValueError("the first barrier of every learner, and every projected barrier, "
                             "must have sign +1")
        grp = np.asarray(self.group)
        if grp.shape != (L,) or not np.issubdtype(grp.dtype, np.integer):
            raise ValueError(f"group must hold one integer per learner ({L}), got {grp!r}")
        for name, arr in (("relative_degree", deg.astype(np.int64)), ("learner",
                          lrn.astype(np.int64)), ("sign", sign), ("group", grp.astype(np.int64))):
            arr = arr.copy()
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    @classmethod
    def uniform(cls, n_barriers: int, relative_degree: int) -> BarrierLayout:
        """``n_barriers`` barriers of one relative degree, one learner each, one group."""
        k = int(n_barriers)
        return cls(np.full(k, int(relative_degree)), np.arange(k), np.ones(k),
                   np.zeros(k, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.relative_degree.shape[0])

    @property
    def n_learners(self) -> int:
        return int(self.group.shape[0])

    @property
    def max_degree(self) -> int:
        return int(self.relative_degree.max())

    @property
    def representatives(self) -> np.ndarray:
        """(L,) the first barrier of every learner."""
        own = np.flatnonzero(self.learner >= 0)
        return own[np.unique(self.learner[own], return_index=True)[1]]

    @property
    def projected(self) -> np.ndarray:
        """(K,) whether each barrier is projected onto the learners (``learner == -1``)."""
        return self.learner < 0

    @property
    def is_uniform(self) -> bool:
        """One relative degree and one learner per barrier (the paper's setting)."""
        deg = self.relative_degree
        return bool(np.all(deg == deg[0]) and self.n_learners == len(self))

    @property
    def one_to_one(self) -> bool:
        """One learner per barrier."""
        return self.n_learners == len(self)
