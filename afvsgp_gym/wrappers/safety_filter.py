"""SafetyFilter: a Gymnasium wrapper projecting every action through the learned HOCBF SOCP."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from afvsgp_gym.cbf import SafetyController
from afvsgp_gym.cbf.config import resolve_miss_probability
from afvsgp_gym.cbf.fastpath import clip
from afvsgp_gym.cbf.learners import LEARNERS, REGISTRY, check_learner_name
from afvsgp_gym.validation import check_choice
from afvsgp_gym.wrappers.obstacle_tracking import ObstacleTracking

__all__ = ["ORACLE_TERMS", "SafetyFilter", "with_env_suggestions"]

#: The oracle's terms: the true plant's, or those lowered by the env's error bound.
ORACLE_TERMS = ("true", "true_robust")


def _layout(base: Any, learner: str) -> Any:
    """The env's barrier layout for ``learner``: ``shared_barrier_layout`` for a learner that
    projects barriers onto shared learners (``REGISTRY[learner].projected``), else
    ``barrier_layout`` (None without one)."""
    if not REGISTRY[check_learner_name(learner)].projected:
        return getattr(base, "barrier_layout", None)
    if not hasattr(type(base), "shared_barrier_layout"):
        raise ValueError(
            f"learner={learner!r} needs an env whose barriers' model errors project onto "
            "shared learners (env.unwrapped.shared_barrier_layout): the Franka envs with "
            "joint-limit barriers and a nominal model that knows the kinematics "
            f"('kinematic', 'perturbed'). {type(base).__name__} has none")
    return base.shared_barrier_layout  # the env says why it cannot, by name


#: ``SafetyFilter``'s default ``learner``: the env's :func:`resolve_learner` suggestion
AUTO_LEARNER = "auto"


def resolve_learner(base: Any, learner: Any) -> Any:
    """``learner``, or for ``"auto"`` the learner the env ``base`` suggests
    (``base.suggested_learner()``: the Franka envs' shared learner where it is as safe and
    faster, see :meth:`~afvsgp_gym.envs.franka.FrankaObstacleEnv.suggested_learner`), else
    the paper's per-barrier ``"afvsgp"``."""
    if not (isinstance(learner, str) and learner == AUTO_LEARNER):
        return learner
    suggest = getattr(base, "suggested_learner", None)
    return str(suggest()) if callable(suggest) else "afvsgp"


def with_env_suggestions(base: Any, learner: str, options: dict[str, Any]) -> dict[str, Any]:
    """A copy of the filter ``options`` with the settings the env ``base`` suggests as defaults
    underneath: ``base.filter_defaults`` (a dict of
    :class:`~afvsgp_gym.cbf.FilterConfig` options; per-barrier options as arrays),
    ``base.activation_distance`` and ``base.learner_defaults[learner]`` (merged key by key
    under the caller's ``learner_kwargs``; a ``learner_kwargs`` that is not a dict is left for
    the controller to refuse by name). A suggested ``calibration``, its
    ``calibration_step`` and ``calibration_gate`` are left out when the caller chooses
    ``calibration`` or sets ``beta = 0`` (no band to calibrate); ``miss_probability`` becomes
    its ``beta``."""
    options = dict(resolve_miss_probability(options))
    suggested_options = dict(getattr(base, "filter_defaults", None) or {})
    if getattr(base, "activation_distance", None) is not None:
        suggested_options.setdefault("activation_distance", base.activation_distance)
    if options.get("beta") == 0 or "calibration" in options:  # no band, or the caller's own
        for name in ("calibration", "calibration_step", "calibration_gate"):
            suggested_options.pop(name, None)
    for name, value in suggested_options.items():
        if isinstance(value, np.ndarray):
            value = float(value) if value.ndim == 0 else tuple(float(v) for v in value.ravel())
        options.setdefault(name, value)
    suggested = (getattr(base, "learner_defaults", None) or {}).get(learner)
    mine = options.get("learner_kwargs")
    if suggested and (mine is None or isinstance(mine, dict)):
        options["learner_kwargs"] = {**suggested, **(mine or {})}
    return options

class SafetyFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Filter the agent's actions with a chance-constrained HOCBF SOCP learned online.

    A thin layer over :class:`afvsgp_gym.cbf.SafetyController` (paper Algorithm 1): at each
    step it reads ``env.unwrapped.barrier_terms("nominal")`` (and ``"true"`` for the oracle),
    one term per barrier, solves the SOCP of eq. 05 around a copy of the proposed action (the
    caller's array is never written), steps the env with the safe action and feeds the eq. 48
    measurement to the learners, one per barrier. The controller, and what it learned, persist
    across episodes; ``reset(seed=s)`` also reseeds its exploration noise from ``s``, so a
    seeded episode is reproducible.

    With a learning learner the applied action carries exploration noise: during warm-up
    (``exploration_noise``, the nominal-only filter) and, by default, a persistent excitation
    afterwards where the learned model is uncertain and decides the action (std up to
    ``online_exploration`` = 0.4 of the half range, scaled by the relative uncertainty of the
    learned action gain), added to the proposal before the projection; set it to 0 for a pure
    projection. With the nominal "zero"
    model nothing can be certified during warm-up: the env must keep obstacles away then (the
    provided scenarios do, for a tracking agent), or pass a recorded ``dataset``.

    The wrapped env must provide ``barrier_terms(model)``, ``dt``, ``relative_degree`` and
    ``n_barriers`` on ``env.unwrapped`` and a finite ``Box`` action space. Its
    ``warmup_steps`` (steps after reset with the obstacles kept away) bounds the default
    number of warm-up samples: ``min(200, warmup_steps - 1)``. Settings the env suggests are
    defaults under the caller's options: ``activation_distance`` and ``learner_defaults``
    (learner name -> ``learner_kwargs``, merged key by key under the caller's; the Franka
    envs suggest 0.15 m and, for their whole-arm sphere sets, AFVSGP with M = 30, P = 500),
    and ``braking_deceleration``. An env with barriers of several relative degrees, or
    barriers that share one model error, describes them in ``barrier_layout``
    (:class:`~afvsgp_gym.types.BarrierLayout`); ``learner="afvsgp-shared"`` takes its
    ``shared_barrier_layout`` instead (barriers projected onto shared learners: the Franka
    envs with joint-limit barriers and a nominal model that knows the kinematics).

    When no action satisfies the chance constraints (the SOCP is infeasible) the filter applies
    a backup action: by default the env's ``backup_action()`` (the provided envs brake: a
    damping torque against the joint or point velocities, which needs no model), else the
    action that maximises the worst predicted margin.

    Args:
        env: the environment.
        learner: one of ``afvsgp_gym.cbf.LEARNERS`` ("none", "oracle", "gp", "vsgp", "sogp",
            "afvsgp", "afvsgp-shared"), or ``"auto"`` (default): the env's suggestion
            (:func:`resolve_learner`; the Franka envs take the shared learner with the
            robot's own model as the prior and many obstacle pairs, the per-barrier
            ``"afvsgp"`` otherwise), which ``learner_name`` then holds.
        backup: ``"env"`` (default: ``env.unwrapped.backup_action()`` if the env has one),
            a callable ``obs -> action`` evaluated on the last observation, or None (the
            max-worst-margin fallback only).
        oracle_terms: the oracle's terms, ``env.unwrapped.barrier_terms(oracle_terms)``:
            ``"true"`` (default) or ``"true_robust"`` (lowered by the env's
            ``true_terms_error_bound()``, e.g. the Franka's joint friction); only with
            ``learner="oracle"``.
        obstacle_estimator: how the filter sees the obstacles of an env with a camera
            (``obstacle_noise``/``obstacle_rate``/``obstacle_delay``): ``"auto"`` (default:
            ``"kalman"`` with a camera), ``"kalman"`` (constant velocity) or ``"kalman-ca"``
            (constant acceleration), whose estimate, predicted over the delay, and covariance
            enter the constraints (each backed off by ``beta`` standard deviations of its
            sensing error, :meth:`~afvsgp_gym.cbf.SafetyController.sensing_std`), or ``"raw"``:
            the camera's reading (and the encoders') taken as the truth
            (:mod:`afvsgp_gym.wrappers.obstacle_tracking`).
        estimator_process_std: the Kalman filter's process noise (default 0.03, m s^-1.5).
        **options: ``dataset`` and the options of :class:`~afvsgp_gym.cbf.FilterConfig`
            (``alpha``, ``beta``, ``activation_distance``, ``warmup_samples``,
            ``exploration_noise``, ``learner_kwargs``, ``online``, ``qp_solver``, ``seed``, ...).

    info keys added at every step: ``"action_proposed"``, ``"action_applied"``,
    ``"filter_active"``, ``"filter_feasible"``, ``"filter_status"``, ``"delta_b_mean"``,
    ``"delta_b_std"`` (per barrier, NaN where not predicted), ``"filter_n_active"`` (barriers
    in the cone program), ``"filter_time_s"``, ``"warmup"``, ``"proposal_true_margin"`` (the
    proposal's smallest true HOCBF constraint value, ground truth for evaluation only),
    ``"learner_error"`` (None, or what a learner raised in this step: the filter went on
    without its prediction, update or fit, and warned once), ``"delta_b_lower"`` (per
    barrier, the lower edge of the band each constraint used: mean plus residual bias minus
    the multiplier times the std; NaN where not predicted), ``"calibration"`` (None, or this
    step's band against its eq. 48 samples: ``samples``, ``misses`` below the band,
    ``within_1std/2std/3std``, ``near_samples`` and ``near_misses`` over the constraints
    within one band-width of binding; :mod:`afvsgp_gym.cbf.calibration`), with an estimator
    ``"obstacle_estimate_error"`` (m, the estimate's largest centre error); ``"delta_b_true"``
    comes from the env. ``filter_fallbacks`` counts infeasible steps since the last reset.

    Example:
        >>> import gymnasium as gym
        >>> import numpy as np
        >>> import afvsgp_gym
        >>> from afvsgp_gym.wrappers import SafetyFilter
        >>> env = gym.make("afvsgp_gym/PointMassObstacle-v0", nominal_model="exact")
        >>> env = SafetyFilter(env, learner="none")
        >>> obs, info = env.reset(seed=0)
        >>> action = np.ones(2, dtype=np.float32)
        >>> obs, reward, terminated, truncated, info = env.step(action)
        >>> action.tolist(), bool(info["filter_feasible"]), info["action_applied"].dtype
        ([1.0, 1.0], True, dtype('float32'))

    Change logs:
     * v0.1.0 - Initially added.
    """

    def __init__(
        self, env: gym.Env, learner: str = AUTO_LEARNER, backup: Any = "env",
        oracle_terms: str = "true", obstacle_estimator: str = "auto",
        estimator_process_std: float = 0.03, **options: Any
    ):
        gym.utils.RecordConstructorArgs.__init__(
            self, learner=learner, backup=backup, oracle_terms=oracle_terms,
            obstacle_estimator=obstacle_estimator,
            estimator_process_std=estimator_process_std, **options)
        gym.Wrapper.__init__(self, env)
        if not (isinstance(learner, str) and (learner == AUTO_LEARNER or learner in LEARNERS)):
            raise ValueError(f"learner must be {AUTO_LEARNER!r} or one of {list(LEARNERS)}. "
                             f"Got: {learner!r}")
        learner = resolve_learner(env.unwrapped, learner)
        #: the learner the filter runs (``learner``, or the env's suggestion for "auto")
        self.learner_name = check_learner_name(learner)
        check_choice("oracle_terms", oracle_terms, ORACLE_TERMS)
        if oracle_terms != "true" and learner != "oracle":
            raise ValueError(f"oracle_terms={oracle_terms!r} needs learner='oracle'. "
                             f"Got: learner={learner!r}")
        self.oracle_terms = oracle_terms
        base = env.unwrapped
        self.tracking = ObstacleTracking(base, obstacle_estimator, estimator_process_std)
        needed = ("barrier_terms", "dt", "relative_degree", "n_barriers")
        if oracle_terms != "true":
            needed += ("true_terms_error_bound",)
        for attr in needed:
            if not hasattr(base, attr):
                raise TypeError(f"SafetyFilter needs env.unwrapped.{attr}; {base} has none")
        space = env.action_space
        if not isinstance(space, gym.spaces.Box):
            raise TypeError(f"SafetyFilter needs a Box action space. Got: {space}")
        low = np.asarray(space.low, dtype=np.float64)
        high = np.asarray(space.high, dtype=np.float64)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError(f"SafetyFilter needs finite action bounds. Got: {space}")
        options = with_env_suggestions(base, learner, options)
        warmup_steps = getattr(base, "warmup_steps", None)
        if "warmup_samples" not in options and warmup_steps is not None:
            options["warmup_samples"] = int(max(2, min(200, warmup_steps - 1)))
        self.controller = SafetyController(
            low,
            high,
            n_barriers=int(base.n_barriers),
            relative_degree=int(base.relative_degree),
            learner=learner,
            layout=_layout(base, learner),
            **options,
        )
        self._dtype = space.dtype
        self.filter_fallbacks = 0
        self._last_obs = None
        if isinstance(backup, str) and backup == "env":
            env_backup = getattr(base, "backup_action", None)
            self._backup = env_backup if callable(env_backup) else None
        elif backup is None:
            self._backup = None
        elif callable(backup):
            self._backup = lambda: backup(self._last_obs)
        else:
            raise ValueError(
                f"backup must be 'env', None or a callable obs -> action. Got: {backup!r}"
            )

    @property
    def learning(self) -> bool:
        """Whether the learners are updated online (set False to freeze them for evaluation)."""
        return self.controller.learning

    @learning.setter
    def learning(self, value: bool) -> None:
        self.controller.learning = bool(value)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.filter_fallbacks = 0
        self.controller.reset_residuals()
        if seed is not None:
            self.controller.reseed(seed)
        self.tracking.reset()
        obs, info = self.env.reset(seed=seed, options=options)
        self.tracking.sense(self.env.unwrapped)
        self._last_obs = obs
        return obs, info

    def step(self, action):
        base = self.env.unwrapped
        proposed = np.array(action, dtype=np.float64)  # a copy: the agent's array is untouched
        shape = self.action_space.shape
        if proposed.shape != shape:
            if proposed.size != math.prod(shape):
                raise ValueError(f"action must have shape {shape}, got {proposed.shape}")
            proposed = proposed.reshape(shape)
        terms = self.tracking.terms(base.barrier_terms("nominal"))
        true_terms = (
            self.tracking.terms(base.barrier_terms(self.oracle_terms))
            if self.controller.uses_true_terms else None
        )
        res = self.controller.filter(proposed, terms, true_terms, self._backup)
        applied = res.u.astype(self._dtype)
        true_margin = self._true_margin(base, proposed)
        obs, reward, terminated, truncated, info = self.env.step(applied)
        self._last_obs = obs
        self.tracking.hold(base)  # the eq. 48 sample: the estimate without the new sample
        self.controller.observe(
            terms, applied.astype(np.float64), base.barrier_terms("nominal"), float(base.dt)
        )
        self.tracking.sense(base)  # the next step's terms: the newest sample fused
        if not res.feasible:
            self.filter_fallbacks += 1
        info = dict(info)
        info.update(
            action_proposed=proposed,
            action_applied=applied,
            filter_active=bool(res.active),
            filter_feasible=bool(res.feasible),
            filter_status=res.status,
            delta_b_mean=res.delta_b_mean,
            delta_b_std=res.delta_b_std,
            filter_n_active=int(res.n_active),
            filter_time_s=float(res.solve_time_s),
            warmup=bool(res.warmup),
            proposal_true_margin=true_margin,
            learner_error=self.controller.learner_error,
            delta_b_lower=res.delta_b_lower,
            calibration=(None if self.controller.last_calibration is None
                         else self.controller.last_calibration.as_dict()),
        )
        if self.tracking.estimator is not None:
            info["obstacle_estimate_error"] = base.sensing_errors()["obstacle_error"]
        return obs, reward, terminated, truncated, info

    def _true_margin(self, base, proposed: np.ndarray) -> float:
        """Ground truth for evaluation (the filter never sees it): the smallest HOCBF
        constraint value (eq. 44, m/s^2 for the provided envs) of the proposal under the true
        model, over all barriers; NaN where the env has no true terms."""
        try:
            terms = getattr(base, "true_state_terms", base.barrier_terms)("true")
            c0, c = self.controller.constraints(terms)
        except (ValueError, TypeError):
            return float("nan")
        margin = c0 + c.dot(clip(proposed, self.controller.low, self.controller.high))
        return float(margin[0] if len(margin) == 1 else margin.min())
