"""Settings of the safety controller, validated once (a frozen dataclass)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields

from afvsgp_gym.validation import check_count, check_real

__all__ = ["DEFAULT_BETA", "DEFAULT_RESIDUAL_CORRECTION", "FilterConfig"]

#: Confidence multiplier of the chance constraint (eq. 49 replaced by a constant, as in
#: Castaneda et al. 2021; the choice is measured in benchmarks/filter.md).
DEFAULT_BETA = 2.5

#: Weight of the residual correction (an exponential average over ~1/0.2 = 5 steps).
DEFAULT_RESIDUAL_CORRECTION = 0.2


@dataclass(frozen=True)
class FilterConfig:
    """Everything the :class:`~afvsgp_gym.cbf.SafetyController` can be told, checked once.

    Attributes
    ----------
    relative_degree : int
        ``r`` of every barrier (2 for the provided envs).
    alpha : float or tuple of float
        Linear class-K gains ``a_1..a_r`` of the HOCBF chain.
    beta : float
        Chance-constraint multiplier on the predicted standard deviation (eq. 49);
        0 gives the mean-only QP.
    barrier_margin : float
        Buffer subtracted from ``h`` in the constraint (units of ``h``): the HOCBF condition
        holds in continuous time; with a zero-order-hold action the sampled ``h`` can dip
        O(dt^2) below the boundary without it.
    activation_distance : float
        A barrier enters the cone program when ``min(h, h + h'/a_1) < activation_distance``
        (units of ``h``); the others are still learned. Outside, ``h >= d`` and
        ``psi_1 = h' + a_1 h >= a_1 d > 0``, so a barrier enters with the HOCBF conditions
        holding; whether ``psi_2 >= 0`` is then feasible within the action bounds depends on
        the system's authority at that distance, hence no finite default: ``inf`` (every
        barrier in the program) unless the env suggests one (``SafetyFilter`` reads
        ``env.unwrapped.activation_distance``; 0.15 m for the Franka, measured in
        benchmarks/filter.md).
    warmup_samples : int
        ``P``: samples collected before the offline hyperparameter fit (Algorithm 1).
    exploration_noise : float
        Std of the Gaussian noise added to the proposal during warm-up, as a fraction of the
        half range of the action bounds.
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
        infeasible) instead of the backup action; False goes to the backup at once.
    learner_kwargs : dict
        Passed to the learner's constructor, on top of the registry's defaults.
    learn_hyperparameters : bool
        Maximise the bound at the end of warm-up (True) or keep the given kernel.
    shared_hyperparameters : bool
        One hyperparameter fit, on the barrier whose warm-up data has the largest mean square,
        shared by all barriers with each barrier's own output scale (True: the cost of one fit
        plus K posteriors), or one fit per barrier (K fits). Measured alike in safety and
        tracking on the Franka sweeps (benchmarks/filter.md).
    online : bool
        Update the learners with every observed sample after warm-up.
    qp_solver : str or None
        qpsolvers backend for the known-model QP (None: clarabel directly).
    compiled_solver : bool or None
        The cone program's compiled several-cones path (``SOCPFilter(compiled=...)``): None
        when it is built, True to require it, False for the numpy paths only.
    compiled_learners : bool or None
        The AFVSGP learners' compiled per-step arithmetic (``AFVSGPBank(compiled=...)``): None
        when it is built, True to require it, False for numpy only.
    seed : int or None
        Seed of the exploration noise.
    """

    relative_degree: int = 2
    alpha: float | tuple[float, ...] = 4.0
    beta: float = DEFAULT_BETA
    barrier_margin: float = 1e-3
    activation_distance: float = float("inf")
    warmup_samples: int = 200
    exploration_noise: float = 0.3
    online_exploration: float = 0.4
    exploration_threshold: float = 1.0
    residual_correction: float = DEFAULT_RESIDUAL_CORRECTION
    relax_to_mean: bool = True
    learner_kwargs: dict = field(default_factory=dict)
    learn_hyperparameters: bool = True
    shared_hyperparameters: bool = True
    online: bool = True
    qp_solver: str | None = None
    compiled_solver: bool | None = None
    compiled_learners: bool | None = None
    seed: int | None = None

    def __post_init__(self) -> None:
        check_count(self.relative_degree, "relative_degree")
        if not isinstance(self.alpha, (int, float)):
            if not isinstance(self.alpha, Sequence):
                raise ValueError(f"alpha must be a float or a sequence of floats, got {self.alpha}")
            object.__setattr__(self, "alpha", tuple(float(a) for a in self.alpha))
        check_real(self.beta, "beta", low=0.0)
        check_real(self.barrier_margin, "barrier_margin", low=0.0)
        if self.activation_distance != float("inf"):
            check_real(self.activation_distance, "activation_distance")
        check_count(self.warmup_samples, "warmup_samples", 2)
        check_real(self.exploration_noise, "exploration_noise", low=0.0)
        check_real(self.online_exploration, "online_exploration", low=0.0)
        check_real(self.exploration_threshold, "exploration_threshold", low=0.0)
        check_real(self.residual_correction, "residual_correction", low=0.0, high=1.0,
                   high_open=True)
        if self.learner_kwargs is None:
            object.__setattr__(self, "learner_kwargs", {})
        if not isinstance(self.learner_kwargs, dict):
            raise ValueError(f"learner_kwargs must be a dict, got {self.learner_kwargs!r}")
        for name in ("compiled_solver", "compiled_learners"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, bool):
                raise ValueError(f"{name} must be None, True or False, got {value!r}")
        if self.seed is not None:
            check_count(self.seed, "seed", 0)

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The keyword options accepted by the controller and the wrapper."""
        return tuple(f.name for f in fields(cls))
