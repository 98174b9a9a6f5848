"""What every obstacle environment shares: argument parsing, barrier caching, the step.

An obstacle env (``FrankaObstacleEnv``, ``PointMassObstacleEnv``) mixes :class:`ObstacleTask`
into its Gymnasium base class and provides the physics and geometry:

- ``_compute_barriers(kind) -> BarrierSet`` for ``kind`` in ``{"zero", "kinematic",
  "perturbed", "exact"}`` at the current state (``"exact"`` is the true plant);
- optionally ``true_terms_error_bound()``, what the ``"exact"`` terms leave out (default 0);
- ``_advance(u) -> bool`` one control period with action ``u``; True when it went unstable;
- ``_contact() -> bool`` any robot geometry touches an obstacle;
- optionally ``_limit_violation() -> bool`` the robot is beyond its own limits (joint range
  stops, speeds; default False), and ``n_obstacle_barriers``: the first barriers are the
  obstacle ones (``info["h"]`` is their minimum; default all of them);
- ``_tracked_point() -> ndarray`` the point that tracks the reference (end-effector);
- ``_get_obs()``, ``time``, ``reference``, ``obstacles``, ``_obstacle_states``,
  ``tracking_radius`` (radius of the tracked point's sphere, for ``reference_h``).

The step and the info keys are then the same for every env (see :meth:`ObstacleTask.step`).
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from afvsgp_gym.envs.scenario import check_action
from afvsgp_gym.types import BarrierSet
from afvsgp_gym.validation import check_choice

__all__ = [
    "BARRIER_MODELS",
    "NOMINAL_MODELS",
    "SCENARIOS",
    "TERMS_MODELS",
    "ObstacleTask",
    "UnknownArgumentError",
    "keyword_defaults",
    "named_arguments",
]

SCENARIOS = ("static", "dynamic", "random")
NOMINAL_MODELS = ("zero", "kinematic", "perturbed", "exact")
BARRIER_MODELS = ("nominal", "true")
#: What ``barrier_terms`` accepts: the models and the robust true terms.
TERMS_MODELS = (*BARRIER_MODELS, "true_robust")
_TERMS_KIND = {"true": "exact", "true_robust": "exact_robust"}


class UnknownArgumentError(TypeError, ValueError):
    """An unknown keyword argument (a TypeError, and a ValueError per the package rules)."""


def named_arguments(init: Callable) -> Callable:
    """Decorate an env's ``__init__`` of explicit (keyword) arguments: an unknown keyword
    raises :class:`UnknownArgumentError` naming the valid ones, in the signature's order
    (Python's own ``TypeError`` names none), before anything is built; ``help()`` and
    ``inspect.signature`` show ``init``'s signature."""
    valid = [name for name in inspect.signature(init).parameters if name != "self"]

    @functools.wraps(init)
    def checked(self, *args: Any, **kwargs: Any) -> None:
        unknown = sorted(set(kwargs) - set(valid))
        if unknown:
            raise UnknownArgumentError(f"unknown argument(s) {unknown}; valid: {valid}")
        init(self, *args, **kwargs)

    return checked


def keyword_defaults(init: Callable) -> dict[str, Any]:
    """The keyword-only arguments of ``init`` and their defaults, in the signature's order
    (an env's ``_DEFAULTS``: its ``## Arguments`` table is tested against them)."""
    return {name: p.default for name, p in inspect.signature(init).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY}


class ObstacleTask:
    """Mixin: barrier terms (cached per state), the safety info and the Gymnasium step."""

    relative_degree = 2
    nominal_model: str
    n_barriers: int
    barrier_names: tuple[str, ...]

    def _invalidate_barriers(self) -> None:
        """Call after every change of the state (the cached terms are stale)."""
        self._barrier_cache: dict[str, BarrierSet] = {}

    def barrier_terms(self, model: str = "nominal") -> BarrierSet:
        """The ``n_barriers`` barriers' terms at the current state (one ``BarrierTerms`` per
        barrier when indexed): ``"true"`` plant, the ``"nominal"`` model, or
        ``"true_robust"``: the true terms with ``lf`` lowered by
        :meth:`true_terms_error_bound`, so that ``lf + lg u`` bounds ``h''`` from below for
        every action (the same as ``"true"`` where the true terms are exact)."""
        if model not in TERMS_MODELS:
            check_choice("model", model, TERMS_MODELS)
        kind = _TERMS_KIND.get(model, self.nominal_model)
        cache = self._barrier_cache
        terms = cache.get(kind)
        if terms is None:
            if kind == "exact_robust":
                terms = cache[kind] = self._robust_true_terms()
            else:
                terms = cache[kind] = self._compute_barriers(kind)
        return terms

    def true_terms_error_bound(self) -> np.ndarray:
        """``(n_barriers,)`` bound on ``|h''_true(u) - (lf + lg u)|`` of the ``"true"`` terms
        over all actions at the current state: 0 here (true terms exact)."""
        return np.zeros(self.n_barriers)

    def _robust_true_terms(self) -> BarrierSet:
        true = self.barrier_terms("true")
        lf = true.lf - self.true_terms_error_bound()
        lf.flags.writeable = False
        return BarrierSet(true.derivatives, lf, true.lg, true.xi)

    def true_state_terms(self, model: str = "true") -> BarrierSet:
        """The terms at the true state (ground truth for evaluation); here the same as
        :meth:`barrier_terms` (the state is known exactly)."""
        return self.barrier_terms(model)

    def barrier_values(self) -> np.ndarray:
        """``(n_barriers,)`` values of h at the true state."""
        return self.true_state_terms("true").h

    def _reference_h(self) -> float:
        """Clearance of the reference point's sphere (``tracking_radius``) from every obstacle."""
        r = self._ref_state[0]
        out = math.inf
        for ob, (po, _, _) in zip(self.obstacles, self._obstacle_states, strict=True):
            d = r - po
            if ob.shape is None:
                out = min(out, math.sqrt(float(d @ d)) - ob.radius - self.tracking_radius)
            else:  # a box, capsule or plane: its signed distance
                out = min(out, ob.distance(d) - self.tracking_radius)
        return out

    @property
    def n_obstacle_barriers(self) -> int:
        """The first ``n_obstacle_barriers`` barriers keep the robot off the obstacles (their
        ``h`` is a distance); any others guard the robot's own limits."""
        return self.n_barriers

    def _limit_violation(self) -> bool:
        """The robot is beyond its own limits (none here)."""
        return False

    def _safety_info(self) -> dict[str, Any]:
        hs = self.barrier_values()
        contact = self._contact()
        limits = self._limit_violation()
        n_obs = self.n_obstacle_barriers
        h_min = float(hs[:n_obs].min()) if n_obs < len(hs) else float(hs.min())
        err = self._tracked_point() - self._ref_state[0]
        return {
            "cost": 1.0 if (h_min < 0.0 or contact or limits) else 0.0,
            "h": h_min,
            "h_per_barrier": hs.copy(),
            "collision": bool(contact),
            "limit_violation": bool(limits),
            "tracking_error": math.sqrt(float(err @ err)),
            "reference_h": self._reference_h(),
        }

    def _get_rew(self, u: np.ndarray) -> tuple[float, dict[str, float]]:
        err = self._tracked_point() - self._ref_state[0]
        track = -self.tracking_weight * math.sqrt(float(err @ err))
        ctrl = -self.control_weight * float(u @ u)
        return track + ctrl, {"reward_tracking": track, "reward_ctrl": ctrl}

    def _reset_info(self) -> dict[str, Any]:
        info = self._safety_info()
        info.update(delta_b_true=np.zeros(self.n_barriers), unstable=False, time=0.0)
        return info

    def step(self, action):
        """Apply ``action`` (clipped to the bounds; NaN, inf or a wrong shape raise
        ``ValueError`` before anything is simulated) for one control period."""
        space = self.action_space
        # np.clip's wrapper costs more than the clipping (check_action has refused NaN)
        u = np.minimum(np.maximum(check_action(action, space.shape), space.low), space.high)
        true = self.true_state_terms("true")
        nom = self.true_state_terms("nominal")
        delta = (true.lf - nom.lf) + (true.lg - nom.lg) @ u
        unstable = self._advance(u)
        reward, reward_info = self._get_rew(u)
        info = self._safety_info()
        info.update(reward_info)
        info.update(delta_b_true=delta, unstable=unstable, time=self.time)
        terminated = unstable or self._out_of_workspace()
        if self.render_mode == "human":  # pragma: no cover - needs a display
            self.render()
        return self._get_obs(), reward, terminated, False, info

    def _out_of_workspace(self) -> bool:
        return False
