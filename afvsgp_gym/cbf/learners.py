"""Learners of the HOCBF model error ``Delta B^(r)``: one per barrier, kept together in a bank.

The safety controller talks to a :class:`LearnerBank`: K learners (one per barrier) fitted
together at the end of warm-up, asked for the affine prediction (eq. 20) of some barriers at
their features, and updated together with one sample per barrier each step. ``REGISTRY``
maps a learner name to how its bank is built; a new learner plugs in with one entry:

- ``"none"``: nominal model only (``Delta B = 0``);
- ``"oracle"``: the filter uses the true model terms (upper bound; nothing is learned);
- ``"gp"``, ``"vsgp"``, ``"sogp"``: exact GP, Titsias VSGP, Bui et al.'s streaming SGP
  (``afvsgp_gym.gp``), one object per barrier;
- ``"afvsgp"``: the paper's method, K learners in stacked arrays
  (:class:`~afvsgp_gym.gp.afvsgp_bank.AFVSGPBank`), so a step costs one set of calls for all;
- ``"afvsgp-shared"``: AFVSGP on the layout's shared learners only (the Franka's: one joint
  acceleration error per joint), every other barrier's model error projected onto them
  (:class:`ProjectedBank`), so the learning costs the same for 1 or 25 obstacles.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

__all__ = [
    "LEARNERS",
    "REGISTRY",
    "LearnerBank",
    "LearnerEntry",
    "MappedBank",
    "ProjectedBank",
    "check_learner_name",
    "make_bank",
    "make_learner",
]

Dataset = tuple[np.ndarray, np.ndarray, np.ndarray]


class LearnerBank(Protocol):
    """K learners of ``Delta B^(r)``, one per barrier."""

    learns: bool

    def fit(self, datasets: Sequence[Dataset], learn_hyperparameters: bool = True,
            groups: np.ndarray | None = None) -> None:
        """Fit learner ``k`` on ``datasets[k] = (xi (N, b), u (N, m), z (N,))``; shared
        hyperparameters only within each of ``groups`` (K,) (None: one group)."""

    def predict_affine(self, xi: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``b`` (k, m+1), ``Sigma`` (k, m+1, m+1) of learners ``rows`` at ``xi`` (k, b)."""

    def update(self, xi: np.ndarray, u: np.ndarray, z: np.ndarray) -> np.ndarray:
        """One sample per learner (``xi`` (K, b), shared ``u``, ``z`` (K,)); NaN rows skipped.
        Returns the (K,) mask of learners updated."""

    def noise_variance(self, rows: np.ndarray) -> np.ndarray:
        """Learned noise variances of learners ``rows`` (k,)."""


class ZeroBank:
    """``Delta B = 0`` with zero covariance (learners ``"none"`` and ``"oracle"``)."""

    learns = False

    def __init__(self, n_barriers: int, action_dim: int, **kwargs):
        if kwargs:
            raise ValueError(f"this learner takes no learner_kwargs. Got: {sorted(kwargs)}")
        self.n_learners, self.action_dim = int(n_barriers), int(action_dim)

    def fit(self, datasets, learn_hyperparameters: bool = True, groups=None) -> None:
        return None

    def predict_affine(self, xi, rows):
        k, d = len(rows), self.action_dim + 1
        return np.zeros((k, d)), np.zeros((k, d, d))

    def update(self, xi, u, z) -> np.ndarray:
        return np.zeros(self.n_learners, dtype=bool)

    def noise_variance(self, rows) -> np.ndarray:
        return np.zeros(len(rows))


class LoopBank:
    """K learner objects of one ``afvsgp_gym.gp`` class, called one by one."""

    learns = True

    def __init__(self, n_barriers: int, action_dim: int, cls_name: str,
                 shared_hyperparameters: bool = True, **kwargs):
        from afvsgp_gym import gp

        self.n_learners, self.action_dim = int(n_barriers), int(action_dim)
        self._cls = getattr(gp, cls_name)
        self._kwargs = kwargs
        try:  # every setting is checked now, not at the end of the warm-up
            self._cls(**kwargs)._check_params()
        except (TypeError, ValueError) as exc:
            raise ValueError(f"learner_kwargs refused by {cls_name}: {exc}") from None
        self.shared = bool(shared_hyperparameters)
        self.learners: list = []

    def _make(self, **override):
        return self._cls(**{**self._kwargs, **override})

    def fit(self, datasets, learn_hyperparameters: bool = True, groups=None) -> None:
        from afvsgp_gym.gp.warmup_fit import fit_shared, fit_with_restarts

        user_kernel = self._kwargs.get("kernel") is not None
        if self.shared:
            groups = np.zeros(len(datasets), dtype=int) if groups is None else np.asarray(groups)
            learners: list = [None] * len(datasets)
            for g in np.unique(groups):
                rows = np.flatnonzero(groups == g)
                fitted = fit_shared(self._make, [datasets[k] for k in rows],
                                    learn_hyperparameters, user_kernel)
                for k, learner in zip(rows, fitted, strict=True):
                    learners[k] = learner
            self.learners = learners
        else:
            self.learners = [fit_with_restarts(self._make, *d, learn_hyperparameters,
                                               user_kernel) for d in datasets]

    def predict_affine(self, xi, rows):
        out = [self.learners[k].predict_affine(xi[j][None]) for j, k in enumerate(rows)]
        d = self.action_dim + 1
        if not out:
            return np.zeros((0, d)), np.zeros((0, d, d))
        return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])

    def update(self, xi, u, z) -> np.ndarray:
        ok = np.isfinite(z) & np.all(np.isfinite(xi), axis=1)
        for k in np.flatnonzero(ok):
            self.learners[k].update(xi[k], u, float(z[k]))
        return ok

    def noise_variance(self, rows) -> np.ndarray:
        return np.array([self.learners[k].noise_variance_ for k in rows])


class AFVSGPLearnerBank(LoopBank):
    """AFVSGP learners fitted one by one (or shared), then run as one :class:`AFVSGPBank`
    (``backend``: whether it runs its compiled core, see that class)."""

    def __init__(self, n_barriers: int, action_dim: int, cls_name: str = "AFVSGP",
                 backend="auto", **kwargs):
        super().__init__(n_barriers, action_dim, cls_name, **kwargs)
        self.backend = backend
        self.bank = None

    def fit(self, datasets, learn_hyperparameters: bool = True, groups=None) -> None:
        from afvsgp_gym.gp.afvsgp_bank import AFVSGPBank

        super().fit(datasets, learn_hyperparameters, groups)
        self.bank = AFVSGPBank.from_learners(self.learners, max_inducing_candidates=1,
                                             backend=self.backend)
        self.learners = []  # the bank holds the state from here on

    def predict_affine(self, xi, rows):
        return self.bank.predict_affine(xi, rows)

    def update(self, xi, u, z) -> np.ndarray:
        return self.bank.update(xi, u, z)

    def noise_variance(self, rows) -> np.ndarray:
        return self.bank.noise_variance[rows]


class _GroupedBank:
    """A bank of one learner per barrier whose hyperparameters are shared per group."""

    def __init__(self, bank: LearnerBank, groups: np.ndarray):
        self.bank, self.groups = bank, groups
        self.learns = bank.learns
        self.predict_affine, self.update = bank.predict_affine, bank.update
        self.noise_variance = bank.noise_variance

    def fit(self, datasets, learn_hyperparameters: bool = True, groups=None) -> None:
        self.bank.fit(datasets, learn_hyperparameters, self.groups)


class MappedBank:
    """Barrier-level view of a bank of ``L`` learners shared by ``K`` barriers
    (:class:`~afvsgp_gym.types.BarrierLayout`): barrier ``k``'s model error is ``sign[k]``
    times learner ``learner[k]``'s, so its prediction is the learner's with the mean's sign
    flipped (the covariance unchanged), and each learner is fitted and updated with its
    representative barrier's samples (the others measure the same quantity, up to the sign
    and rounding). A learner serving several barriers of the program is predicted once (their
    features are the same: the layout's contract)."""

    learns = True

    def __init__(self, bank: LearnerBank, layout):
        self.bank, self.layout = bank, layout
        self._reps = layout.representatives
        self._learner = layout.learner
        self._sign = layout.sign

    def fit(self, datasets, learn_hyperparameters: bool = True, groups=None) -> None:
        self.bank.fit([datasets[k] for k in self._reps], learn_hyperparameters,
                      self.layout.group)

    def predict_affine(self, xi, rows):
        learners = self._learner[rows]
        # each learner once (at one of its rows: their features agree), in learner order;
        # O(k + L) by a slot table, not a sort (np.unique costs more than a small prediction)
        slot = np.full(len(self._reps), -1, dtype=np.intp)
        slot[learners] = np.arange(len(learners))
        uniq = np.flatnonzero(slot >= 0)
        b, sigma = self.bank.predict_affine(xi[slot[uniq]], uniq)
        if len(uniq) < len(learners):  # shared learners: back to one row per barrier
            slot[uniq] = np.arange(len(uniq))
            at = slot[learners]
            b, sigma = b[at], sigma[at]
        return b * self._sign[rows][:, None], sigma

    def update(self, xi, u, z) -> np.ndarray:
        reps = self._reps
        return self.bank.update(xi[reps], u, z[reps])[self._learner]

    def noise_variance(self, rows) -> np.ndarray:
        return self.bank.noise_variance(self._learner[rows])


class ProjectedBank(MappedBank):
    """:class:`MappedBank` whose projected barriers (``learner == -1``) have no learner: barrier
    ``k``'s model error is ``W_k @ e``, ``W = BarrierSet.projection`` (K, L), of the ``L``
    learners' quantities ``e`` (affine in ``u``, independent across learners), so its
    prediction is the exact linear map of theirs (issue 45):

        b_k = sum_l W_kl b_l,        Sigma_k = sum_l W_kl^2 Sigma_l.

    Every learner is predicted at its representative's features, once per call, whatever the
    number of projected barriers; only the learners' own barriers feed them samples."""

    def __init__(self, bank: LearnerBank, layout):
        super().__init__(bank, layout)
        self._own = ~layout.projected
        self._w2: np.ndarray | None = None  # projection**2 of the last prediction (K, L)

    def predict_projected(self, xi, projection, rows):
        """``b`` (k, m+1), ``Sigma`` (k, m+1, m+1) of barriers ``rows``: ``xi`` (K, b) and
        ``projection`` (K, L) are the whole set's (the learners' representatives may be
        outside ``rows``)."""
        own = self._own[rows]
        if own.all():
            return MappedBank.predict_affine(self, xi[rows], rows)
        n_l = len(self._reps)
        b_l, s_l = self.bank.predict_affine(xi[self._reps], np.arange(n_l))
        w = np.asarray(projection, dtype=np.float64)[rows]
        self._w2 = np.zeros((len(self._own), n_l))
        self._w2[rows] = w2 = w * w
        b = w @ b_l
        sigma = np.einsum("kl,lij->kij", w2, s_l)
        if own.any():  # their own learner's prediction, sign applied
            mine = rows[own]
            lrn = self._learner[mine]
            b[own] = b_l[lrn] * self._sign[mine][:, None]
            sigma[own] = s_l[lrn]
        return b, sigma

    def update(self, xi, u, z) -> np.ndarray:
        reps = self._reps
        done = self.bank.update(xi[reps], u, z[reps])
        return np.where(self._own, done[self._learner], bool(done.any()))

    def noise_variance(self, rows) -> np.ndarray:
        """The learners' noise variances; a projected barrier's through the projection of the
        last prediction (``sum_l W_kl^2 s2_l``; NaN before any)."""
        rows = np.asarray(rows)
        s2 = self.bank.noise_variance(np.arange(len(self._reps)))
        out = np.full(len(rows), np.nan)
        own = self._own[rows]
        out[own] = s2[self._learner[rows[own]]]
        if self._w2 is not None and not own.all():
            out[~own] = self._w2[rows[~own]] @ s2
        return out


@dataclass(frozen=True)
class LearnerEntry:
    """How the bank of one learner name is built: ``bank(n_barriers, action_dim, gp_class,
    **kwargs)`` (None: :class:`ZeroBank`); ``gp_class`` names the ``afvsgp_gym.gp`` class;
    ``default_kwargs`` are the settings used unless the user overrides them; ``true_terms``
    marks the oracle (the filter then uses the true model's terms); ``projected`` a learner
    that needs a layout with projected barriers (the env's ``shared_barrier_layout``)."""

    bank: type | None = None
    gp_class: str | None = None
    default_kwargs: dict = field(default_factory=dict)
    true_terms: bool = False
    projected: bool = False


#: Learner name -> bank construction. AFVSGP inside the filter keeps a window of P = 1000
#: samples with phi = 0.999 and M = 40 inducing points, rebuilds [r, S] from the window every
#: 25 P updates (the drift of the recursion stays ~1e-13 relative over 2e4 updates) and makes
#: at most one inducing-set change per step (docs/filter.md, docs/learners.md). The Franka
#: envs suggest M = 30, P = 500 for their whole-arm sphere sets
#: (``env.unwrapped.learner_defaults``).
REGISTRY: dict[str, LearnerEntry] = {
    "none": LearnerEntry(),
    "oracle": LearnerEntry(true_terms=True),
    "gp": LearnerEntry(LoopBank, "ExactGP"),
    "vsgp": LearnerEntry(LoopBank, "VSGP"),
    "sogp": LearnerEntry(LoopBank, "SOGP"),
    "afvsgp": LearnerEntry(AFVSGPLearnerBank, "AFVSGP",
                           {"window": 1000, "forgetting": 0.999, "num_inducing": 40,
                            "refresh_every": 25000}),
    "afvsgp-shared": LearnerEntry(AFVSGPLearnerBank, "AFVSGP",
                                  {"window": 1000, "forgetting": 0.999, "num_inducing": 40,
                                   "refresh_every": 25000}, projected=True),
}

#: Names accepted by the safety filter.
LEARNERS: tuple[str, ...] = tuple(REGISTRY)


def check_learner_name(name) -> str:
    """Return ``name`` if it is in :data:`LEARNERS`, else raise ``ValueError`` listing them."""
    if not isinstance(name, str) or name not in REGISTRY:
        raise ValueError(f"learner must be one of {list(LEARNERS)}. Got: {name!r}")
    return name


def make_bank(name: str, n_barriers: int, action_dim: int, learner_kwargs: dict | None = None,
              shared_hyperparameters: bool = True, backend="auto",
              layout=None) -> LearnerBank:
    """The bank of K = ``n_barriers`` learners called ``name`` (``learner_kwargs`` on top of
    the registry's defaults go to each learner's constructor; ``backend``: whether the AFVSGP
    bank runs its compiled core, see :class:`~afvsgp_gym.gp.afvsgp_bank.AFVSGPBank`). With a
    :class:`~afvsgp_gym.types.BarrierLayout` whose barriers share learners, a
    :class:`MappedBank` of its ``L`` learners."""
    entry = REGISTRY[check_learner_name(name)]
    if entry.bank is None:
        return ZeroBank(n_barriers, action_dim, **(learner_kwargs or {}))
    kwargs = {**entry.default_kwargs, **(learner_kwargs or {})}
    if issubclass(entry.bank, AFVSGPLearnerBank):  # the only bank with a compiled core
        kwargs["backend"] = backend
    shared = layout is not None and not layout.one_to_one
    bank = entry.bank(layout.n_learners if shared else n_barriers, action_dim,
                      entry.gp_class, shared_hyperparameters=shared_hyperparameters, **kwargs)
    if layout is None or not shared:
        if layout is not None and np.any(layout.group != layout.group[0]):
            return _GroupedBank(bank, layout.group)
        return bank
    return ProjectedBank(bank, layout) if layout.projected.any() else MappedBank(bank, layout)


def make_learner(name: str, action_dim: int, **kwargs):
    """One unfitted ``afvsgp_gym.gp`` learner called ``name`` (the registry's filter
    defaults are not applied: these are the GP classes' own, as in the paper's Table I)."""
    entry = REGISTRY[check_learner_name(name)]
    if entry.gp_class is None:
        raise ValueError(f"learner {name!r} has no GP object")
    from afvsgp_gym import gp

    return getattr(gp, entry.gp_class)(**kwargs)
