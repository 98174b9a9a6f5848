"""Standalone learned HOCBF safety controller (paper Algorithm 1), no simulator needed.

Example
-------
>>> import numpy as np
>>> from afvsgp_gym.types import BarrierTerms
>>> ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none", alpha=2.0)
>>> terms = [BarrierTerms(np.array([0.1, -0.2]), 0.0, np.array([1.0, 0.0]), np.zeros(3))]
>>> res = ctrl.filter(np.array([-1.0, 0.5]), terms)
>>> res.feasible, bool(res.active), np.round(res.u, 3).tolist()
(True, True, [0.404, 0.5])

In a real robot loop: ``res = ctrl.filter(u_nom, terms, u_backup=brake)``; apply ``res.u`` for
one control period ``dt``; read the new terms; ``ctrl.observe(terms, res.u, new_terms, dt)``.
``terms`` holds one :class:`~afvsgp_gym.types.BarrierTerms` per barrier (or a
:class:`~afvsgp_gym.types.BarrierSet`). ``u_backup`` (optional) is the action to apply when no
action satisfies the chance constraints, e.g. a joint-damping brake; without it the filter
falls back to the action that maximises the worst margin.

One step has two parts with one job each: :meth:`SafetyController.filter` assembles the
constraints (eq. 45 plus the learned mean and covariance, eq. 51) of the barriers near an
obstacle and solves the cone program (eq. 05); :meth:`SafetyController.observe` measures the
step (eq. 48), feeds the residual observer with the prediction the filter used (a
:class:`StepPrediction`) and updates the learners (Algorithm 1).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.linalg.lapack import dpotrf

from afvsgp_gym import _compiled
from afvsgp_gym.cbf.calibration import (
    CalibrationCounts,
    ConformalMultiplier,
    near_binding,
    score_counts,
    scores,
)
from afvsgp_gym.cbf.config import FilterConfig, resolve_miss_probability
from afvsgp_gym.cbf.exploration import Exploration, exploration_scale
from afvsgp_gym.cbf.hocbf import HOCBF, BarrierConstraints
from afvsgp_gym.cbf.learners import REGISTRY, check_learner_name, make_bank
from afvsgp_gym.cbf.measurement import measure_samples
from afvsgp_gym.cbf.residuals import ResidualObserver
from afvsgp_gym.cbf.socp import SOCPFilter
from afvsgp_gym.types import BarrierLayout, BarrierSet
from afvsgp_gym.validation import check_count

__all__ = ["FilterResult", "SafetyController", "StepPrediction", "fit_bank", "split_samples"]

_step = _compiled.extension("step")

#: Program sizes (barriers in the program) whose solvers the constructor builds ahead: the
#: activation distance keeps the program to a few tens of barriers in the shipped scenes, and
#: building every size of a scene's hundreds took ~1 s per filter.
PREPARED_PROGRAM_SIZES = 48

#: Options that were replaced, and by what (named in the error for the old name).
_REPLACED_OPTIONS = {"compiled_solver": "backend", "compiled_learners": "backend"}


@dataclass(frozen=True)
class FilterResult:
    """One filtered action.

    Attributes
    ----------
    u : ndarray of shape (m,)
        Safe action, finite and inside the bounds.
    feasible : bool
        False when no action satisfied the constraints (backup or fallback applied).
    active : bool
        True when the filter changed the (clipped) proposed action, or fell back.
    status : str
        ``"inactive"``, the solver status, ``"backup:..."`` (infeasible: the backup action),
        ``"fallback:..."`` (infeasible: max worst margin) or ``"invalid_input"``.
    margins : ndarray of shape (K,)
        Chance-constraint margins at ``u`` (NaN for barriers outside the program).
    delta_b_mean, delta_b_std : ndarray of shape (K,)
        Learned mean and standard deviation of ``Delta B^(r)`` at ``u`` (eq. 51; NaN where
        not predicted).
    delta_b_lower : ndarray of shape (K,)
        The lower edge of the band each constraint used at ``u``: ``delta_b_mean`` plus the
        residual bias minus the multiplier (``beta``, or the conformal one) times
        ``delta_b_std`` (NaN where not predicted; the mean without learning).
    solve_time_s : float
        Wall time of prediction and cone program.
    warmup : bool
        True while Algorithm 1's warm-up collects its first samples.
    n_active : int
        Number of barriers in the cone program.
    """

    u: np.ndarray
    feasible: bool
    active: bool
    status: str
    margins: np.ndarray
    delta_b_mean: np.ndarray
    delta_b_std: np.ndarray
    solve_time_s: float
    warmup: bool = False
    n_active: int = 0
    delta_b_lower: np.ndarray | None = None


@dataclass(frozen=True)
class StepPrediction:
    """What the filter predicted for the step it just filtered (read by ``observe``).

    ``rows`` the barriers predicted, ``mean`` (k, m+1) and ``cov`` (k, m+1, m+1) their
    affine prediction, ``action`` the action returned; ``center`` (k,) the band's center at
    ``action`` (mean plus residual bias), ``std`` (k,) its standard deviation, ``lower``
    (k,) its lower edge."""

    rows: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    action: np.ndarray
    center: np.ndarray | None = None
    std: np.ndarray | None = None
    lower: np.ndarray | None = None
    margin: np.ndarray | None = None


def cone_matrix(sigma: np.ndarray, beta: float) -> np.ndarray:
    """``G = beta L'`` with ``Sigma = L L'`` (eq. 05 with the standard deviation, eq. 51):
    ``||G ubar|| = beta sqrt(ubar' Sigma ubar)``. The Cholesky factor (LAPACK ``potrf``) when
    Sigma is numerically positive definite, else the eigen-factor ``diag(sqrt(max(w, 0))) V'``."""
    sym = 0.5 * (sigma + sigma.T)
    upper, info = dpotrf(sym, lower=0, clean=1)
    if info == 0:
        upper *= beta
        return upper
    w, v = np.linalg.eigh(sym)
    return (beta * np.sqrt(np.maximum(w, 0.0)))[:, None] * v.T


def cone_matrices(sigma: np.ndarray, beta: float,
                  backend: str | _compiled.Backend = "auto") -> np.ndarray:
    """:func:`cone_matrix` of every ``Sigma`` in the stack ``sigma`` (k, m+1, m+1): one
    batched Cholesky when all are numerically positive definite, else one by one (the batch
    in the compiled step glue unless ``backend`` is ``"numpy"``, see
    :mod:`afvsgp_gym._compiled`). A zero ``Sigma`` (a barrier the learned error cannot
    reach: a projected row ``W_k = 0``, such as a sphere of link 1 against a table, which
    the first joint only turns in its plane) has the zero factor, and the rest stay batched."""
    if sigma.ndim == 3 and len(sigma) > 1:
        zero = ~sigma.reshape(len(sigma), -1).any(axis=1)
        if zero.any():
            out = np.zeros(sigma.shape)
            if not zero.all():
                out[~zero] = cone_matrices(sigma[~zero], beta, backend)
            return out
    if (_compiled.resolve(backend, ("step",)).step and sigma.ndim == 3
            and 1 <= sigma.shape[1] <= 17):
        out = np.empty(sigma.shape)
        n, c = sigma.shape[:2]
        if _step.cone_factors(n, c, np.ascontiguousarray(sigma, dtype=np.float64),
                              float(beta), out) == 0:
            return out
    sym = 0.5 * (sigma + sigma.transpose(0, 2, 1))
    try:
        low = np.linalg.cholesky(sym)
    except np.linalg.LinAlgError:
        return np.array([cone_matrix(s, beta) for s in sym])
    out = low.transpose(0, 2, 1)
    out *= beta
    return out


def chance_margins(u: np.ndarray, a0: np.ndarray, a: np.ndarray, G: np.ndarray) -> np.ndarray:
    """``a0 + a @ u - ||G ubar||`` per constraint (eq. 05)."""
    gu = G[:, :, 0] + G[:, :, 1:] @ u
    return a0 + a @ u - np.sqrt(np.einsum("ki,ki->k", gu, gu))


class SafetyController:
    """Learned HOCBF safety filter: chance-constrained SOCP + one learner per barrier.

    Parameters
    ----------
    action_low, action_high : array_like of shape (m,)
        Action bounds (the filter never leaves them).
    n_barriers : int
        Number of barriers K (one learner each, unless ``layout`` shares them).
    learner : str
        One of :data:`afvsgp_gym.cbf.LEARNERS`.
    layout : BarrierLayout or None
        Each barrier's relative degree and which barriers share one learner
        (:class:`~afvsgp_gym.types.BarrierLayout`; its largest degree must be
        ``relative_degree``); None: ``n_barriers`` barriers of ``relative_degree``, one
        learner each.
    dataset : tuple or list of tuples or None
        ``(xi (N, b), u (N, m), z (N,))`` recorded beforehand (one tuple for every barrier,
        or one per barrier): the learners are fitted at construction and warm-up is skipped.
    **options
        The fields of :class:`~afvsgp_gym.cbf.config.FilterConfig` (``alpha``, ``beta``,
        ``activation_distance``, ``warmup_samples``, ``exploration_noise``,
        ``online_exploration``, ``residual_correction``, ``learner_kwargs``, ``online``,
        ``seed``, ...), or ``config=FilterConfig(...)``; ``miss_probability=p`` in place of
        ``beta`` sets ``beta = Phi^-1(1 - p)``.
    """

    def __init__(self, action_low, action_high, n_barriers: int = 1, learner: str = "afvsgp",
                 *, layout: BarrierLayout | None = None, dataset=None,
                 config: FilterConfig | None = None, **options: Any):
        self.learner_name = check_learner_name(learner)
        self.n_barriers = K = check_count(n_barriers, "n_barriers")
        unknown = sorted(set(options) - set(FilterConfig.option_names()))
        if unknown:
            valid = list(FilterConfig.option_names())
            hint = "".join(f" ({name} was replaced by {_REPLACED_OPTIONS[name]})"
                           for name in unknown if name in _REPLACED_OPTIONS)
            raise ValueError(f"unknown option(s) {unknown}; valid: {valid}{hint}")
        options = resolve_miss_probability(options)
        self.config = cfg = replace(config or FilterConfig(), **options)
        #: the compiled extensions this filter runs (``cfg.backend`` resolved)
        self.backend = _compiled.resolve(cfg.backend)
        if layout is None:
            layout = BarrierLayout.uniform(K, cfg.relative_degree)
        elif not isinstance(layout, BarrierLayout) or len(layout) != K:
            raise ValueError(f"layout must be a BarrierLayout of n_barriers={K} barriers. "
                             f"Got: {layout!r}")
        elif layout.max_degree != cfg.relative_degree:
            raise ValueError(f"layout's largest relative degree ({layout.max_degree}) must be "
                             f"relative_degree={cfg.relative_degree}")
        if REGISTRY[self.learner_name].projected and not layout.projected.any():
            raise ValueError(f"learner={learner!r} needs a layout with projected barriers "
                             "(BarrierLayout.learner == -1, e.g. the Franka envs' "
                             "shared_barrier_layout)")
        self.layout = layout
        self.hocbf = HOCBF(cfg.relative_degree, cfg.alpha)
        self.barriers = BarrierConstraints(
            layout.relative_degree, cfg.alpha, cfg.per_barrier("braking_deceleration", K),
            cfg.per_barrier("activation_distance", K), cfg.per_barrier("first_gain", K))
        #: the paper's setting: one degree, the linear chain, one learner per barrier
        self._plain = self.barriers.uniform_linear and layout.one_to_one
        self._degrees = None if layout.is_uniform else layout.relative_degree
        self._margin_gain = float(np.prod(self.hocbf.gains))  # d psi_r / d h
        self.socp = SOCPFilter(action_low, action_high, qp_solver=cfg.qp_solver,
                               backend=self.backend)
        self.low, self.high = self.socp.low, self.socp.high
        self.action_dim = self.socp.m
        entry = REGISTRY[self.learner_name]
        self.uses_true_terms = entry.true_terms
        self.bank = make_bank(self.learner_name, self.n_barriers, self.action_dim,
                              cfg.learner_kwargs, cfg.shared_hyperparameters,
                              self.backend, layout)
        self.learns = self.bank.learns
        #: barriers projected onto the learners (``BarrierSet.projection``), if any
        self._projected = bool(self.learns and layout.projected.any())
        self.prepare_programs(PREPARED_PROGRAM_SIZES)  # (at most n_barriers)
        self.exploration = Exploration(self.low, self.high, cfg.exploration_noise,
                                       cfg.online_exploration, cfg.seed)
        self.residuals = ResidualObserver(self.n_barriers, cfg.residual_correction,
                                          self.backend)
        self.learning = bool(cfg.online)
        #: the online multiplier or margin (``calibration`` not off), else None
        self.conformal = None
        if self.learns and cfg.calibrates:
            modes = cfg.calibration_modes(K)
            steps = np.where(modes == "off", 0.0, cfg.per_barrier("calibration_step", K))
            # a projected barrier's band has its own multiplier (it has no learner)
            groups = np.where(layout.projected, layout.n_learners + np.arange(K),
                              layout.learner)
            self.conformal = ConformalMultiplier(groups, cfg.beta, steps,
                                                 additive=modes == "conformal-additive")
        self._scored: tuple | None = None  # (z, center, std, lower, near) of the last step
        self._calibration: CalibrationCounts | None = None
        self.fitted = not self.learns
        self._buffer: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        #: fit in :meth:`observe` once the warm-up samples are in (False: the caller fits
        #: :meth:`warmup_samples` elsewhere and calls :meth:`install_fitted`; the samples
        #: after the warm-up's are not kept meanwhile)
        self.fit_at_warmup = True
        self._pending: StepPrediction | None = None
        self.n_update_failures = 0
        self.n_skipped_samples = 0
        self.last_error: str | None = None
        #: the learner failures of the current step (``filter`` then ``observe``), else None
        self.learner_error: str | None = None
        self._warned = False
        if dataset is not None and self.learns:
            self.fit(dataset)

    # ------------------------------------------------------------------ state
    def prepare_programs(self, n_constraints: int | None = None) -> None:
        """Build clarabel's solver objects for programs of 1 to ``n_constraints`` barriers
        (default: all of them) now, so that the control loop only updates them. The
        constructor builds those up to :data:`PREPARED_PROGRAM_SIZES`; a larger program builds
        its solver on first use (~1 ms once per size; the answer does not depend on when:
        :mod:`~afvsgp_gym.cbf.cone_programs`). A hard real-time loop calls this with no
        argument before it starts."""
        n = self.n_barriers if n_constraints is None else check_count(n_constraints,
                                                                      "n_constraints")
        n = min(n, self.n_barriers)
        self.socp.prepare(n, cones=False)  # the QP: known model, mean fallback
        if self.learns and self.config.beta > 0:
            self.socp.prepare(n, cones=True)

    @property
    def beta(self) -> float:
        return self.config.beta

    @property
    def residual_bias(self) -> np.ndarray:
        """(K,) current residual correction per barrier."""
        return self.residuals.bias

    def reset_residuals(self) -> None:
        """Forget the residual correction (e.g. at an episode reset: the state jumps)."""
        self.residuals.reset()
        self._pending = None

    def reseed(self, seed: int) -> None:
        """Reseed the exploration noise (the wrapper derives it from ``reset(seed=...)``)."""
        self.exploration.reseed(seed)

    @property
    def warming_up(self) -> bool:
        """True until the learners are fitted (Algorithm 1 warm-up)."""
        return not self.fitted

    def warmup_samples(self, out: Sequence[np.ndarray] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The warm-up samples collected so far as arrays: ``xi`` (K, N, b), ``u`` (N, m),
        ``z`` (K, N) (None before any; into ``out``, three arrays of
        :meth:`warmup_shapes`, when given); :func:`split_samples` makes :meth:`dataset` of
        them."""
        buf = self._buffer
        if not buf:
            return None
        if out is None:
            out = [None, None, None]
        xi = np.stack([b[0] for b in buf], axis=1, out=out[0])
        u = np.stack([b[1] for b in buf], out=out[1])
        z = np.stack([b[2] for b in buf], axis=1, out=out[2])
        return xi, u, z

    def warmup_shapes(self, n_samples: int | None = None, feature_dim: int | None = None
                      ) -> tuple[tuple[int, ...], ...]:
        """The shapes of :meth:`warmup_samples`' arrays with ``n_samples`` (default: those
        collected so far) of ``feature_dim`` features (default: the collected ones'; before
        any, ``feature_dim`` is needed)."""
        if feature_dim is None and not self._buffer:
            raise ValueError("feature_dim is needed before any warm-up sample is collected")
        n = len(self._buffer) if n_samples is None else int(n_samples)
        b = self._buffer[0][0].shape[1] if feature_dim is None else int(feature_dim)
        k, m = self.n_barriers, self.action_dim
        return (k, n, b), (n, m), (k, n)

    def dataset(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Warm-up samples collected so far, one ``(xi, u, z)`` tuple per barrier (rows with
        non-finite values left out)."""
        samples = self.warmup_samples()
        if samples is None:
            m = self.action_dim
            return [(np.zeros((0, 0)), np.zeros((0, m)), np.zeros(0))
                    for _ in range(self.n_barriers)]
        return split_samples(*samples)

    @property
    def warmup_complete(self) -> bool:
        """Warming up with :attr:`~afvsgp_gym.cbf.config.FilterConfig.warmup_samples` samples
        collected: what :meth:`observe` fits on, unless ``fit_at_warmup`` is False (then
        whoever turned it off fits, e.g. in another process, and calls
        :meth:`install_fitted`)."""
        return self.learns and not self.fitted and \
            len(self._buffer) >= self.config.warmup_samples

    def fit(self, dataset) -> SafetyController:
        """Fit every learner offline on ``dataset`` (one tuple, or one per barrier)."""
        if isinstance(dataset, tuple):
            dataset = [dataset] * self.n_barriers
        if len(dataset) != self.n_barriers:
            raise ValueError(
                f"dataset must hold one (xi, u, z) tuple or {self.n_barriers}. Got: {len(dataset)}"
            )
        fit_bank(self.bank, dataset, self.action_dim, self.config.learn_hyperparameters)
        self.fitted = True
        return self

    def install_fitted(self, bank) -> None:
        """Use ``bank``, this controller's bank fitted elsewhere on :meth:`warmup_samples`
        (:func:`fit_bank`; the bridge's :class:`~afvsgp_gym.robots.background_fit.BackgroundFit`),
        from the next step on; the warm-up samples are dropped."""
        if type(bank) is not type(self.bank):
            raise ValueError(f"bank must be a fitted {type(self.bank).__name__}. Got: {bank!r}")
        self.bank = bank
        self.fitted = True
        self._buffer = []

    # ------------------------------------------------------------------ filter
    def _terms(self, terms, name: str) -> BarrierSet:
        bset = BarrierSet.stack(terms)
        if len(bset) != self.n_barriers:
            raise ValueError(f"{name} must hold {self.n_barriers} BarrierTerms. Got: {len(bset)}")
        return bset

    def _check_projection(self, bset: BarrierSet) -> None:
        """A layout with projected barriers needs their projection onto the learners."""
        shape = (self.n_barriers, self.layout.n_learners)
        if bset.projection is None or np.shape(bset.projection) != shape:
            raise ValueError(
                f"terms.projection must have shape {shape} (each barrier's model error as a "
                f"linear map of the {shape[1]} learners'), for the layout's projected "
                f"barriers. Got: {None if bset.projection is None else np.shape(bset.projection)}"
                " (a nominal model that knows nothing, e.g. the Franka's 'zero', has none: "
                "use a per-barrier learner such as 'afvsgp')")

    def _active_rows(self, derivs: np.ndarray, ok: np.ndarray | None) -> np.ndarray:
        """Barriers in the program: within their activation distance
        (:meth:`BarrierConstraints.active_rows`; for the linear chain ``min(h, h + h'/a_1) <
        activation_distance``), and every barrier with non-finite terms (``ok`` False, so that
        the program reports them; ``ok`` None: all finite)."""
        if not self._plain:
            rows = self.barriers.active_rows(derivs)
            if ok is None:
                return rows
            inside = np.zeros(len(ok), dtype=bool)
            inside[rows] = True
            return np.flatnonzero(inside | ~ok)
        h = derivs[:, 0]
        near = np.minimum(h, h + derivs[:, 1] / self.hocbf.gains[0]) if derivs.shape[1] > 1 else h
        inside = near < self.config.activation_distance
        return np.flatnonzero(inside if ok is None else inside | ~ok)

    def _finite_active_rows(self, c0: np.ndarray, c: np.ndarray,
                            bset: BarrierSet) -> np.ndarray | None:
        """:meth:`_active_rows` in the compiled step glue when every term is finite; None when
        one is not, or the backend does not run the glue, or it does not take these arrays
        (float64, C-ordered); the paper's setting only (one degree, linear chain)."""
        if not self.backend.step or not self._plain:
            return None
        d, xi = bset.derivatives, bset.xi
        K, r = d.shape
        rows = np.empty(K, dtype=np.int64)
        gain = float(self.hocbf.gains[0]) if r > 1 else 1.0
        try:
            n = _step.active_rows(K, c.shape[1], r, xi.shape[1], c0, c, d, xi, gain,
                                  float(self.config.activation_distance), rows)
        except ValueError:
            return None
        return rows[:n] if n >= 0 else None

    def _learned_terms(self, a0: np.ndarray, a: np.ndarray, bvec: np.ndarray,
                       rows: np.ndarray, sig: np.ndarray) -> tuple[bool, np.ndarray | None]:
        """The learned mean and residual bias added to every constraint of the program in
        place (``a0 += bvec[:, 0] + bias[rows]``, ``a += bvec[:, 1:]``, eq. 05) and the cone
        matrices :func:`cone_matrices` (``beta > 0``, else None), in the compiled step glue:
        ``(True, G)``, or ``(False, None)`` with nothing changed when the backend does not run
        it."""
        if not self.backend.step:
            return False, None
        beta = float(self.config.beta)
        n, c = sig.shape[:2]
        G = np.empty((n, c, c)) if beta > 0 else None
        try:
            rc = _step.learned_terms(n, c - 1, self.n_barriers, a0, a, bvec,
                                     self.residuals.bias, rows, sig, beta, G)
        except (ValueError, TypeError):
            return False, None
        if rc != 0:  # a covariance not numerically positive definite: the eigen-factor
            G = cone_matrices(sig, beta, self.backend)
        return True, G

    def filter(self, u_nom, terms, true_terms=None, u_backup=None) -> FilterResult:
        """Project ``u_nom`` onto the (chance-)constrained safe set (eq. 05).

        ``terms`` are the nominal barrier terms (one per barrier); the oracle learner uses
        ``true_terms`` instead. ``u_backup`` (array of shape (m,) or a zero-argument callable
        returning one, evaluated only when needed) is applied, clipped to the bounds, when
        the program is infeasible or fails (status ``"backup:..."``); without it, or if it is
        not finite, the action maximising the worst margin is used (``"fallback:..."``).
        Never raises for NaN values: they give the flagged fallback.
        """
        t0 = time.perf_counter()
        self.learner_error = None  # a new step
        K, m = self.n_barriers, self.action_dim
        if self.uses_true_terms:
            if true_terms is None:
                raise ValueError(f"learner {self.learner_name!r} needs true_terms")
            bset = self._terms(true_terms, "true_terms")
        else:
            bset = self._terms(terms, "terms")
            if self._projected:
                self._check_projection(bset)
        u_nom = np.array(u_nom, dtype=np.float64).ravel()  # a copy
        if u_nom.shape != (m,):
            raise ValueError(f"u_nom must have shape ({m},). Got: {u_nom.shape}")
        warm = self.warming_up
        if self.learns and warm:
            if self.config.warmup_exploration == "backup" and u_backup is not None:
                backup = self.socp._backup_action(u_backup)
                if backup is not None:
                    u_nom = backup
            u_nom = self.exploration.perturb(u_nom, warm=True)
        c0, c = self.constraints(bset)
        if self.config.barrier_margin:
            gain = self._margin_gain if self._plain else self.barriers.margin_gain
            c0 = c0 - self.config.barrier_margin * gain
        if bset.covariance is not None and self.config.beta > 0:
            c0 = c0 - self.config.beta * self.sensing_std(bset)
        ok = None
        rows = self._finite_active_rows(c0, c, bset)
        if rows is None:
            # a finite sum means every term is finite: one reduction per array
            if not math.isfinite(float(c0.sum()) + float(c.sum())
                                 + float(bset.derivatives.sum()) + float(bset.xi.sum())):
                ok = np.isfinite(c0 + c.sum(axis=1) + bset.derivatives.sum(axis=1)
                                 + bset.xi.sum(axis=1))
            rows = self._active_rows(bset.derivatives, ok)
        a0, a = c0[rows], c[rows]  # copies (integer indices)
        if ok is not None:  # any non-finite term makes its constraint invalid (flagged fallback)
            a0 = np.where(ok[rows], a0, np.nan)
        G = None
        if warm or not self.learns:
            pred_rows = rows[:0]
        else:
            pred_rows = rows if ok is None else rows[ok[rows]]
        bvec = sig = None
        if len(pred_rows):
            try:
                bvec, sig = (self.bank.predict_projected(bset.xi, bset.projection, pred_rows)
                             if self._projected
                             else self.bank.predict_affine(bset.xi[pred_rows], pred_rows))
                bias = self.residuals.bias[pred_rows]  # (a copy) the bias this step uses
                mult, marg = self._band(pred_rows)
                sig_cone = (sig if self.conformal is None or not self.conformal.any_multiplier
                            else sig * ((mult / self.config.beta) ** 2)[:, None, None])
                done, G = (self._learned_terms(a0, a, bvec, pred_rows, sig_cone)
                           if ok is None else (False, None))
                if done:  # every barrier of the program predicted
                    if marg is not None:
                        a0 -= marg
                    u_nom = self._excite(u_nom, pred_rows, sig, a0, a)
                else:
                    where = slice(None) if ok is None else np.searchsorted(rows, pred_rows)
                    a0[where] += bvec[:, 0] + bias
                    if marg is not None:
                        a0[where] -= marg
                    a[where] += bvec[:, 1:]
                    u_nom = self._excite(u_nom, pred_rows, sig, a0[where], a[where])
                    if self.config.beta > 0:
                        G = np.zeros((len(rows), m + 1, m + 1))
                        G[where] = cone_matrices(sig_cone, self.config.beta, self.backend)
            except Exception as exc:  # a learner failure must not stop the loop
                self._learner_failed(exc, "prediction")
                a0 = np.full(len(rows), np.nan)
                pred_rows, bvec, sig, G = rows[:0], None, None, None
        res = self.socp.solve(u_nom, a0, a, G, u_backup)
        if not res.feasible and G is not None and self.config.relax_to_mean:
            # graceful degradation: the mean-only constraints (beta = 0) before the backup
            cones = self._relaxed_cones(G, rows)
            mean_res = None if cones is G else self.socp.solve(u_nom, a0, a, cones, None)
            if mean_res is not None and mean_res.feasible:
                res = replace(mean_res, feasible=False, status=f"relaxed:{res.status}",
                              margins=chance_margins(mean_res.u, a0, a, G))
        u = res.u
        margins = np.full(K, np.nan)
        margins[rows] = res.margins
        fill = np.nan if self.learns else 0.0  # nothing learned: Delta B = 0 exactly
        mean = np.full(K, fill)
        std = mean.copy()
        lower = mean.copy()
        if bvec is not None:
            ubar = np.concatenate([[1.0], u])
            mean[pred_rows] = bvec @ ubar
            s = np.sqrt(np.maximum(((sig @ ubar) * ubar).sum(axis=1), 0.0))
            std[pred_rows] = s
            center = mean[pred_rows] + bias
            edge = center - mult * s if marg is None else center - mult * s - marg
            lower[pred_rows] = edge
            self._pending = StepPrediction(pred_rows, bvec, sig, u.copy(), center, s, edge,
                                           margins[pred_rows])
        else:
            self._pending = None if warm else StepPrediction(rows[:0], bvec, sig, u.copy())
        return FilterResult(
            u=u,
            feasible=res.feasible,
            active=res.status != "inactive",
            status=res.status,
            margins=margins,
            delta_b_mean=mean,
            delta_b_std=std,
            solve_time_s=time.perf_counter() - t0,
            warmup=warm,
            n_active=len(rows),
            delta_b_lower=lower,
        )

    def _relaxed_cones(self, G: np.ndarray, rows: np.ndarray) -> np.ndarray | None:
        """The cones the mean-only relaxation keeps (``relax_to_mean``): those of the
        barriers of relative degree 1 in the program, none (None) without such barriers, and
        ``G`` itself when every barrier of the program has relative degree 1 (nothing to
        relax: the program is not solved again)."""
        if self._degrees is None:
            return None if self.config.relative_degree != 1 else G
        keep = self._degrees[rows] == 1
        if not keep.any():
            return None
        if keep.all():
            return G
        out = G.copy()
        out[~keep] = 0.0
        return out

    def _band(self, rows: np.ndarray) -> tuple[float | np.ndarray, np.ndarray | None]:
        """The band's multiplier of barriers ``rows`` (``beta``, or the conformal one per
        row) and its additive margin (None for none)."""
        if self.conformal is None:
            return float(self.config.beta), None
        if self.conformal.any_margin:
            return self.conformal.multiplier(rows), self.conformal.margins(rows)
        return self.conformal.multiplier(rows), None

    def constraints(self, terms) -> tuple[np.ndarray, np.ndarray]:
        """The nominal HOCBF constraints (eq. 45) of every barrier, ``c0 + c @ u >= 0``:
        ``c0`` (K,), ``c`` (K, m), each barrier with its relative degree and class-K
        functions (:class:`~afvsgp_gym.cbf.hocbf.BarrierConstraints`)."""
        bset = BarrierSet.stack(terms)
        if self._plain:
            return self.hocbf.constraints(bset)
        return self.barriers.constraints(bset)

    def sensing_std(self, terms) -> np.ndarray:
        """Standard deviation (K,) of each constraint's ``c0`` (eq. 45) from the sensing:
        ``sqrt(g' C g)`` with ``C`` the terms' ``covariance`` of ``[h, ..., h^(r-1), lf]`` and
        ``g`` the gradient of ``c0`` in them (``dc0/dlf = 1``; the derivatives' by central
        differences through :meth:`constraints`, so every class-K function is covered), to
        first order. The filter backs each constraint off by ``beta`` of it: the chance
        constraint on the sensing error alone, and with a learned band the two standard
        deviations add (at least ``sqrt`` of the summed variances: conservative)."""
        bset = BarrierSet.stack(terms)
        cov = bset.covariance
        if cov is None:
            return np.zeros(len(bset))
        d = bset.derivatives
        r = d.shape[1]
        if np.shape(cov) != (len(d), r + 1, r + 1):
            raise ValueError(f"covariance must have shape ({len(d)}, {r + 1}, {r + 1}) (the "
                             f"barriers' [h, ..., h^(r-1), lf]). Got: {np.shape(cov)}")
        grad = np.empty((len(d), r + 1))
        grad[:, r] = 1.0
        for i in range(r):
            step = 1e-6 * np.maximum(1.0, np.abs(d[:, i]))
            up, down = d.copy(), d.copy()
            up[:, i] += step
            down[:, i] -= step
            c_up = self.constraints(BarrierSet(up, bset.lf, bset.lg, bset.xi))[0]
            c_down = self.constraints(BarrierSet(down, bset.lf, bset.lg, bset.xi))[0]
            grad[:, i] = (c_up - c_down) / (2.0 * step)
        var = np.einsum("ki,kij,kj->k", grad, cov, grad)
        return np.sqrt(np.maximum(var, 0.0))

    def _excite(self, u_nom: np.ndarray, rows: np.ndarray, sig: np.ndarray, a0: np.ndarray,
                a: np.ndarray) -> np.ndarray:
        """Online exploration only where it is needed, and only as much as it is needed.

        Where: for some barrier in the program the model is uncertain at the proposal
        (predicted standard deviation of ``Delta B`` above ``exploration_threshold`` noise
        standard deviations) and that uncertainty decides the action (the mean margin
        ``a0 + a @ u`` is below ``2 beta`` standard deviations). How much: the noise's std is
        ``online_exploration * min(1, rho)``, ``rho`` the largest relative uncertainty of the
        action gain among those barriers, ``sqrt(trace(H Sigma_uu H)) / ||H a||`` (``Sigma_uu``
        the action block of the eq. 51 covariance, ``a`` the constraint's gradient in the
        action, nominal plus learned, ``H`` the half range of the bounds): exploration is for
        identifying the gain, so a prior that gives it (a small ``rho``) excites less. A
        proposal that is safe with margin, or with a confident model, passes unchanged."""
        if self.exploration.online_noise <= 0 or not math.isfinite(float(u_nom.sum())):
            return u_nom
        rho = exploration_scale(sig, a0, a, u_nom, self.low, self.high,
                                np.sqrt(self.bank.noise_variance(rows)),
                                self.exploration.half_range, self.config.exploration_threshold,
                                2.0 * max(self.config.beta, 1.0), self.backend)
        if rho < 0.0:  # no barrier gated (NaN is not: full noise)
            return u_nom
        return self.exploration.perturb(u_nom, warm=False, scale=rho)

    # ------------------------------------------------------------------ learning
    def observe(self, terms_before, u_applied, terms_after, dt: float) -> np.ndarray:
        """Build the eq. 48 samples for the step just taken and update the learners.

        Returns the measurements ``z`` (K,) (NaN where skipped). Never raises for NaN data
        (such samples are skipped and counted in ``n_skipped_samples``).
        """
        K = self.n_barriers
        self._scored = self._calibration = None
        if not self.learns:
            return np.full(K, np.nan)
        before = self._terms(terms_before, "terms_before")
        after = self._terms(terms_after, "terms_after")
        u = np.asarray(u_applied, dtype=np.float64).ravel()
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and positive. Got: {dt!r}")
        if u.shape != (self.action_dim,):
            raise ValueError(f"u_applied must have shape ({self.action_dim},). Got: {u.shape}")
        with np.errstate(invalid="ignore", over="ignore"):
            xi, z, n_bad = measure_samples(before, u, after, dt, self._degrees, self.backend)
        if n_bad:  # some sample is not finite
            bad = ~(np.isfinite(z) & np.all(np.isfinite(xi), axis=1))
            self.n_skipped_samples += int(bad.sum())
            z = np.where(bad, np.nan, z)
        if not math.isfinite(float(u.sum())):
            return z
        if self.warming_up:
            if len(self._buffer) < self.config.warmup_samples:
                self._buffer.append((xi, u.copy(), z))
            # (absent from a controller pickled before the switch existed)
            if self.warmup_complete and getattr(self, "fit_at_warmup", True):
                self._fit_warmup()
            return z
        self._update_residuals(u, z)
        if self.learning:
            try:
                self.bank.update(xi, u, z)
            except Exception as exc:
                self.n_update_failures += 1
                self._learner_failed(exc, "online update")
        return z

    def _fit_warmup(self) -> None:
        """Algorithm 1, line 3: fit on the warm-up samples; on failure keep the newest half."""
        try:
            self.fit(self.dataset())
            self._buffer = []
        except Exception as exc:
            self.n_update_failures += 1
            self._learner_failed(exc, "fit at the end of the warm-up")
            del self._buffer[: len(self._buffer) // 2]

    def _learner_failed(self, exc: Exception, where: str) -> None:
        """A learner raised inside the loop: the step goes on (the prediction's barriers are
        flagged invalid, an update or fit is skipped); ``learner_error`` and ``last_error``
        say so, and the first failure is warned (``RuntimeWarning``), never silent."""
        self.last_error = f"{where}: {type(exc).__name__}: {exc}"
        self.learner_error = (self.last_error if self.learner_error is None
                              else f"{self.learner_error}; {self.last_error}")
        if not getattr(self, "_warned", False):  # (absent from a controller pickled before)
            self._warned = True
            warnings.warn(f"the {self.learner_name} learner failed ({self.last_error}); the "
                          "filter goes on (failures are reported in "
                          "SafetyController.learner_error and info['learner_error'], this "
                          "warning only once)", RuntimeWarning, stacklevel=3)

    def _update_residuals(self, u: np.ndarray, z: np.ndarray) -> None:
        """Residual observer with the prediction the filter used for this very action; the
        band's calibration (and its conformal correction) from the same prediction."""
        pred, self._pending = self._pending, None
        if pred is None or pred.mean is None:
            self.residuals.reset()  # no barrier predicted: every bias returns to 0
            return
        d = pred.action - u  # the applied action may be a float32 copy of the filtered one
        if not float(d @ d) <= 1e-12 * (1.0 + float(u @ u)):
            self.residuals.reset()
            return
        if pred.center is not None and len(pred.rows):
            near = near_binding(pred.margin, pred.center, pred.lower)
            self._scored = (z[pred.rows], pred.center, pred.std, pred.lower, near)
            if self.conformal is not None:
                noise = (np.sqrt(self.bank.noise_variance(pred.rows))
                         if self.conformal.any_margin else None)
                sc = scores(*self._scored[:3])
                if self.config.calibration_gate:  # only where a miss could decide
                    sc = np.where(near, sc, np.nan)
                self.conformal.update(pred.rows, sc, pred.std, noise)
        ubar = np.concatenate([[1.0], u])
        self.residuals.update(pred.rows, pred.mean @ ubar, z=z)

    # ------------------------------------------------------------------ diagnostics
    @property
    def last_calibration(self) -> CalibrationCounts | None:
        """The band of the last observed step against its eq. 48 samples: scored barriers,
        misses below the band and the 1, 2, 3 std coverages
        (:mod:`afvsgp_gym.cbf.calibration`), and those of the near-binding rows; None when no
        barrier was predicted. Counted when read."""
        if getattr(self, "_scored", None) is None:  # (absent from a controller pickled before)
            return None
        if self._calibration is None:
            self._calibration = score_counts(*self._scored)[1]
        return self._calibration

    @property
    def noise_variances(self) -> np.ndarray | None:
        """(K,) learned noise variances after warm-up (None before, or without learning)."""
        if not self.learns or self.warming_up:
            return None
        return self.bank.noise_variance(np.arange(self.n_barriers))


def split_samples(xi: np.ndarray, u: np.ndarray,
                  z: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """One ``(xi, u, z)`` tuple per barrier of the stacked samples ``xi`` (K, N, b), ``u``
    (N, m), ``z`` (K, N), the rows with non-finite values left out."""
    out = []
    for k in range(len(z)):
        ok = np.isfinite(z[k]) & np.all(np.isfinite(xi[k]), axis=1)
        out.append((xi[k][ok], u[ok], z[k][ok]))
    return out


def fit_bank(bank, dataset, action_dim: int, learn_hyperparameters: bool) -> None:
    """Fit ``bank`` on ``dataset`` (one ``(xi, u, z)`` per barrier; rows with a non-finite
    value left out): Algorithm 1, line 3."""
    clean = []
    for xi, u, z in dataset:
        xi = np.asarray(xi, np.float64)
        u = np.asarray(u, np.float64).reshape(len(xi), action_dim)
        z = np.asarray(z, np.float64).ravel()
        ok = np.all(np.isfinite(xi), axis=1) & np.all(np.isfinite(u), axis=1) & np.isfinite(z)
        clean.append((xi[ok], u[ok], z[ok]))
    bank.fit(clean, learn_hyperparameters)
