"""Settings of the safety controller, validated once (a frozen dataclass)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from afvsgp_gym._compiled import BACKENDS, Backend
from afvsgp_gym.cbf.calibration import CALIBRATION_MODES, beta_for_miss_probability, miss_target
from afvsgp_gym.validation import check_count, check_real

__all__ = ["DEFAULT_BETA", "DEFAULT_RESIDUAL_CORRECTION", "FilterConfig",
           "resolve_miss_probability"]

#: Confidence multiplier of the chance constraint (eq. 49 replaced by a constant, as in
#: Castaneda et al. 2021; the choice: docs/filter.md, "Defaults that differ from the paper").
DEFAULT_BETA = 2.5

#: Weight of the residual correction (an exponential average over ~1/0.2 = 5 steps).
DEFAULT_RESIDUAL_CORRECTION = 0.2


def _per_barrier(value, name: str, ok, what: str,
                 nan_ok: bool = False) -> float | tuple[float, ...]:
    """A float, or a tuple of floats from a sequence or array, each ``ok`` (or NaN with
    ``nan_ok``); ``ValueError`` naming ``name`` and the entry otherwise."""
    scalar = np.ndim(value) == 0
    try:
        values = np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or a sequence of numbers. Got: {value!r}")\
            from None
    if values.ndim != 1 or values.size == 0:
        raise ValueError(f"{name} must be a number or a 1-D sequence of numbers. Got: {value!r}")
    for i, v in enumerate(values):
        if math.isnan(v) and nan_ok:
            continue
        if math.isnan(v) or not ok(v):
            where = "" if scalar else f"[{i}]"
            raise ValueError(f"{name}{where} must be {what}. Got: {v!r}")
    return float(values[0]) if scalar else tuple(float(v) for v in values)


#: Values of ``FilterConfig.warmup_exploration``.
WARMUP_EXPLORATION = ("proposal", "backup")


@dataclass(frozen=True)
class FilterConfig:
    """Everything the :class:`~afvsgp_gym.cbf.SafetyController` can be told, checked once.

    Attributes
    ----------
    relative_degree : int
        ``r`` of every barrier (2 for the provided envs); with a
        :class:`~afvsgp_gym.types.BarrierLayout` of mixed degrees, the largest.
    alpha : float or tuple of float
        Linear class-K gains ``a_1..a_r`` of the HOCBF chain.
    beta : float
        Chance-constraint multiplier on the predicted standard deviation (eq. 49);
        0 gives the mean-only QP. The band promises a one-sided miss probability
        ``Phi(-beta)`` per barrier and step (:attr:`miss_probability`); the controller and
        the wrapper also take that probability as the option ``miss_probability`` in its
        place (:func:`resolve_miss_probability`).
    calibration : str or tuple of str
        One mode for all barriers or one per barrier (a learner's barriers may mix the
        multiplier and the margin; ``"off"`` rows keep the paper's band).
        ``"off"`` (default): the band is ``beta`` predicted standard deviations, as the paper's;
        ``"conformal"``: each learner's multiplier is adapted online so that the long-run rate
        of eq. 48 samples below the band meets ``Phi(-beta)`` whatever the model's
        misspecification, never below ``beta``
        (:class:`~afvsgp_gym.cbf.calibration.ConformalMultiplier`, its guarantee and
        assumptions); ``"conformal-additive"``: the band keeps ``beta`` standard deviations and
        each learner adapts an additive margin the same way. Needs ``beta > 0``. Either way
        the filter reports the band it used (``FilterResult.delta_b_lower``) and each step's
        misses and coverages (``SafetyController.last_calibration``).
    calibration_step : float or tuple of float
        ``eta`` of the conformal correction, one for all barriers (``> 0``) or one per barrier
        (``>= 0``; a learner takes the largest of its barriers'; 0 keeps that learner's band
        the paper's): standard deviations per miss (the multiplier), or the learner's noise
        standard deviations per miss (the margin). E.g. on the Franka envs
        ``[0.0] * (env.unwrapped.n_barriers - 28) + [1.0] * 28`` corrects the joint-limit
        barriers' band only.
    calibration_gate : bool
        Adapt the conformal correction only on the steps where a miss could decide the
        constraint: its margin at the applied action is below the band's width (``center -
        lower``), so one band width more of model error would violate it. The long-run miss
        rate then holds on that subsequence (a rule fixed before the sample is seen); far
        from binding, where a miss changes nothing, the band is not widened.
    barrier_margin : float
        Buffer subtracted from ``h`` in the constraint (units of ``h``): the HOCBF condition
        holds in continuous time; with a zero-order-hold action the sampled ``h`` can dip
        O(dt^2) below the boundary without it.
    activation_distance : float or tuple of float
        ``D >= 0``, one for all barriers or one per barrier (units of each barrier's ``h``). A
        barrier enters the cone program when ``h < D`` or, relative degree >= 2,
        ``psi_1 < alpha_1(D)`` (for the linear chain: ``min(h, h + h'/a_1) < D``); the others
        are still learned. Outside, ``h >= D`` and ``psi_1 >= alpha_1(D) > 0``, so a barrier
        enters with the HOCBF conditions holding; whether ``psi_2 >= 0`` is then feasible
        within the action bounds depends on the system's authority (see
        ``braking_deceleration``), hence no finite default: ``inf`` (every barrier in the
        program) unless the env suggests one (``SafetyFilter`` reads
        ``env.unwrapped.activation_distance``; for the Franka 0.15 m for the obstacle
        barriers and its own values for the joint-limit barriers).
    braking_deceleration : float or tuple of float
        ``A > 0``, one for all barriers or one per barrier (units of ``h`` per s^2; only
        relative degree 2): the first class-K function becomes the braking curve of
        :func:`~afvsgp_gym.cbf.hocbf.braking_alpha`, so the approach speed never exceeds what
        a deceleration ``A`` can stop, and ``psi_2 >= 0`` stays feasible wherever the actions
        can make ``h'' >= A`` (:class:`~afvsgp_gym.cbf.hocbf.BarrierConstraints`). ``inf``
        (default, the paper's) is the linear ``a_1 h``; the Franka envs suggest values
        derived from the torque limits.
    first_gain : float or tuple of float
        The gain ``a_1`` of the first class-K function, one for all barriers or one per
        barrier, in place of ``alpha``'s first (NaN or the default ``nan``: ``alpha``'s;
        relative degrees 1 and 2 only). The Franka envs suggest a faster one for their joint
        speed barriers (relative degree 1) than for the others.
    warmup_samples : int
        ``P``: samples collected before the offline hyperparameter fit (Algorithm 1).
    exploration_noise : float
        Std of the Gaussian noise added during warm-up, as a fraction of the half range of
        the action bounds.
    warmup_exploration : str
        What the warm-up noise is added to: ``"proposal"`` (the paper's Algorithm 1: the
        policy's action, through the nominal-only filter: safe only while the policy is, since
        a nominal model that knows nothing certifies nothing) or ``"backup"`` (the backup
        action, e.g. the env's damping brake, through the same filter: the policy does not act
        until the learners are fitted, so the warm-up is safe whatever it proposes; needs a
        ``u_backup``, else the proposal is used).
    online_exploration : float
        Largest std of the noise added after warm-up (same units), for persistent
        excitation, at the steps where it is needed (see ``exploration_threshold``); the
        std is this times ``min(1, rho)``, ``rho`` the relative uncertainty of the learned
        action gain (see :meth:`SafetyController._excite`).
    exploration_threshold : float
        After warm-up the proposal is excited only when, for some barrier in the program, the
        predicted standard deviation of ``Delta B`` at the proposal is above this many of its
        learner's noise standard deviations and the mean margin is below ``2 beta`` of them
        (the uncertainty decides the action); otherwise the proposal passes unchanged.
    residual_correction : float
        Weight ``w`` in [0, 1) of the residual observer (see
        :class:`~afvsgp_gym.cbf.residuals.ResidualObserver`); 0 disables it.
    relax_to_mean : bool
        When no action satisfies the chance constraints, apply the solution of the mean-only
        constraints (``beta = 0``) if it exists (status ``"relaxed:..."``, flagged
        infeasible) instead of the backup action; False (default) goes to the backup at
        once. The relaxation drops the band exactly where the learner is unsure: with nothing
        known, an arm held millimetres above a table by infeasible programs sank into it on
        the relaxed steps' confidently wrong mean, and on the one-obstacle suite it had more
        episodes with cost than the brake (docs/adversarial.md). The barriers of relative
        degree 1 keep their band in the relaxation: they have no state to absorb one control
        period's model error (a joint speed barrier relaxed to a confidently wrong mean let a
        policy's full torque add 0.8 rad/s to joint 4 in one period), and the backup brake
        always satisfies them.
    learner_kwargs : dict
        Passed to the learner's constructor, on top of the registry's defaults.
    learn_hyperparameters : bool
        Maximise the bound at the end of warm-up (True) or keep the given kernel.
    shared_hyperparameters : bool
        One hyperparameter fit, on the barrier whose warm-up data has the largest mean square,
        shared by all barriers with each barrier's own output scale (True: the cost of one fit
        plus K posteriors), or one fit per barrier (K fits). Measured alike in safety and
        tracking on the Franka sweeps (docs/filter.md, docs/learners.md).
    online : bool
        Update the learners with every observed sample after warm-up.
    qp_solver : str or None
        qpsolvers backend for the known-model QP (None: clarabel directly).
    backend : str
        Which code runs the filter's arithmetic: ``"auto"`` (default) the compiled extensions
        that are built (the cone program's one- and several-cones paths, the controller's
        step glue, the AFVSGP learners' core), ``"numpy"`` the numpy paths only (the
        reference; no compiled code runs), ``"compiled"`` all three extensions
        (``ImportError`` naming those that were not built when the filter is made). For
        diagnostics, a ``Backend`` of some extensions only, e.g. ``_compiled.resolve("compiled",
        ("step", "bank"))`` for the cone program in numpy (:mod:`afvsgp_gym._compiled`).
    seed : int or None
        Seed of the exploration noise.
    """

    relative_degree: int = 2
    alpha: float | tuple[float, ...] = 4.0
    beta: float = DEFAULT_BETA
    calibration: str | tuple[str, ...] = "off"
    calibration_step: float | tuple[float, ...] = 0.5
    calibration_gate: bool = False
    barrier_margin: float = 1e-3
    activation_distance: float | tuple[float, ...] = float("inf")
    braking_deceleration: float | tuple[float, ...] = float("inf")
    first_gain: float | tuple[float, ...] = float("nan")
    warmup_samples: int = 200
    exploration_noise: float = 0.3
    warmup_exploration: str = "proposal"
    online_exploration: float = 0.4
    exploration_threshold: float = 1.0
    residual_correction: float = DEFAULT_RESIDUAL_CORRECTION
    relax_to_mean: bool = False
    learner_kwargs: dict = field(default_factory=dict)
    learn_hyperparameters: bool = True
    shared_hyperparameters: bool = True
    online: bool = True
    qp_solver: str | None = None
    backend: str | Backend = "auto"
    seed: int | None = None

    def __post_init__(self) -> None:
        check_count(self.relative_degree, "relative_degree")
        if not isinstance(self.alpha, (int, float)):
            if not isinstance(self.alpha, Sequence):
                raise ValueError(f"alpha must be a float or a sequence of floats, got {self.alpha}")
            object.__setattr__(self, "alpha", tuple(float(a) for a in self.alpha))
        check_real(self.beta, "beta", low=0.0)
        modes = self.calibration
        if isinstance(modes, (list, tuple, np.ndarray)):
            modes = tuple(modes)
            if not modes:
                raise ValueError("calibration must be a mode or one mode per barrier. Got: ()")
            object.__setattr__(self, "calibration", modes)
        else:
            modes = (modes,)
        for mode in modes:
            if not isinstance(mode, str) or mode not in CALIBRATION_MODES:
                raise ValueError(f"calibration must be one of {list(CALIBRATION_MODES)} or one "
                                 f"of them per barrier. Got: {self.calibration!r}")
        if self.calibrates and not self.beta > 0:
            raise ValueError(f"calibration={self.calibration!r} needs beta > 0. "
                             f"Got: beta={self.beta!r}")
        object.__setattr__(self, "calibration_step", _per_barrier(
            self.calibration_step, "calibration_step",
            (lambda v: v > 0) if np.ndim(self.calibration_step) == 0 else (lambda v: v >= 0),
            "> 0 (one value) or >= 0 (one per barrier), and finite"))
        if not np.all(np.isfinite(self.calibration_step)):
            raise ValueError(f"calibration_step must be finite. Got: {self.calibration_step!r}")
        check_real(self.barrier_margin, "barrier_margin", low=0.0)
        object.__setattr__(self, "activation_distance", _per_barrier(
            self.activation_distance, "activation_distance", lambda v: v >= 0,
            ">= 0 (inf allowed)"))
        object.__setattr__(self, "braking_deceleration", _per_barrier(
            self.braking_deceleration, "braking_deceleration", lambda v: v > 0,
            "> 0 (inf allowed)"))
        object.__setattr__(self, "first_gain", _per_barrier(
            self.first_gain, "first_gain", lambda v: math.isfinite(v) and v > 0,
            "finite and > 0", nan_ok=True))
        check_count(self.warmup_samples, "warmup_samples", 2)
        check_real(self.exploration_noise, "exploration_noise", low=0.0)
        if self.warmup_exploration not in WARMUP_EXPLORATION:
            raise ValueError(f"warmup_exploration must be one of {list(WARMUP_EXPLORATION)}. "
                             f"Got: {self.warmup_exploration!r}")
        check_real(self.online_exploration, "online_exploration", low=0.0)
        check_real(self.exploration_threshold, "exploration_threshold", low=0.0)
        check_real(self.residual_correction, "residual_correction", low=0.0, high=1.0,
                   high_open=True)
        if self.learner_kwargs is None:
            object.__setattr__(self, "learner_kwargs", {})
        if not isinstance(self.learner_kwargs, dict):
            raise ValueError(f"learner_kwargs must be a dict, got {self.learner_kwargs!r}")
        if not isinstance(self.backend, Backend) and (
                not isinstance(self.backend, str) or self.backend not in BACKENDS):
            raise ValueError(f"backend must be one of {list(BACKENDS)}. Got: {self.backend!r}")
        if self.seed is not None:
            check_count(self.seed, "seed", 0)

    def per_barrier(self, name: str, n_barriers: int) -> np.ndarray:
        """The option ``name`` (``activation_distance``, ``braking_deceleration``,
        ``first_gain`` or ``calibration_step``) as an array of ``n_barriers`` values;
        ``ValueError`` when a tuple has another length."""
        value = getattr(self, name)
        if isinstance(value, tuple):
            if len(value) != n_barriers:
                raise ValueError(f"{name} must be one value or {n_barriers} (one per barrier). "
                                 f"Got: {len(value)} values")
            return np.array(value, dtype=np.float64)
        return np.full(n_barriers, float(value))

    @property
    def calibrates(self) -> bool:
        """Whether some barrier's band is corrected online (``calibration`` not all off)."""
        modes = self.calibration if isinstance(self.calibration, tuple) else (self.calibration,)
        return any(mode != "off" for mode in modes)

    def calibration_modes(self, n_barriers: int) -> np.ndarray:
        """``calibration`` as an array of ``n_barriers`` modes; ``ValueError`` when a tuple
        has another length."""
        modes = self.calibration
        if isinstance(modes, tuple):
            if len(modes) != n_barriers:
                raise ValueError(f"calibration must be one mode or {n_barriers} (one per "
                                 f"barrier). Got: {len(modes)} modes")
            return np.array(modes, dtype=object)
        return np.full(n_barriers, modes, dtype=object)

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The keyword options accepted by the controller and the wrapper (the fields, and
        ``miss_probability`` for ``beta``)."""
        return (*(f.name for f in fields(cls)), "miss_probability")

    @property
    def miss_probability(self) -> float:
        """``Phi(-beta)``: the one-sided miss probability the band promises per barrier and
        step (eq. 49)."""
        return miss_target(self.beta)


def resolve_miss_probability(options: dict) -> dict:
    """``options`` with ``miss_probability`` (the band's one-sided miss probability per barrier
    and step, in (0, 0.5]) replaced by the ``beta = Phi^-1(1 - miss_probability)`` it means
    (eq. 49); unchanged without it. ``ValueError`` when both are given (one would be lost)."""
    if "miss_probability" not in options:
        return options
    options = dict(options)
    p = options.pop("miss_probability")
    if "beta" in options:
        raise ValueError(f"give beta or miss_probability, not both. Got: beta={options['beta']!r}"
                         f", miss_probability={p!r}")
    options["beta"] = beta_for_miss_probability(p)
    return options
