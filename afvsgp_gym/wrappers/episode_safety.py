"""EpisodeSafetyStats: per-episode safety and filter counts, at every step of the env."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym

__all__ = ["EPISODE_SAFETY_FIELDS", "EpisodeSafetyStats"]

#: Keys of ``info["episode_safety"]``.
EPISODE_SAFETY_FIELDS = (
    "steps",
    "return",
    "success",
    "cost_steps",
    "cost_steps_after_warmup",
    "violation_steps",
    "contact_steps",
    "limit_steps",
    "min_h",
    "interventions",
    "infeasible_steps",
    "backup_steps",
    "relaxed_steps",
    "warmup_steps",
    "saturated_steps",
)


class EpisodeSafetyStats(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Count, over every step of an episode, what the safety report needs; at the episode's
    last step ``info["episode_safety"]`` holds the counts (keys :data:`EPISODE_SAFETY_FIELDS`).

    Place it between a :class:`~afvsgp_gym.wrappers.SafetyFilter` (or the bare env) and an
    :class:`~afvsgp_gym.wrappers.ActionRepeat`, so every filtered step is counted even when the
    agent acts less often.

    - ``cost_steps``: ``info["cost"] > 0``
      (:data:`~afvsgp_gym.evaluation.COST_DEFINITION`); ``cost_steps_after_warmup`` those with
      ``info["warmup"]`` False (the filter's learners fitted; every step without a filter);
      ``violation_steps`` h < 0; ``contact_steps`` ``info["collision"]``; ``limit_steps``
      ``info["limit_violation"]``; ``min_h`` the smallest h.
    - ``interventions``: ``info["filter_active"]``; ``infeasible_steps`` not
      ``info["filter_feasible"]``, split by ``info["filter_status"]`` into ``backup_steps``
      (the backup or max-margin fallback applied) and ``relaxed_steps`` (the mean-only
      solution applied); ``warmup_steps`` with ``info["warmup"]``.
    - ``success``: some step had ``info["success"]``; ``saturated_steps``:
      ``info["torque_saturated"]``.

    Example:
        >>> import gymnasium as gym
        >>> import numpy as np
        >>> import afvsgp_gym
        >>> env = EpisodeSafetyStats(gym.make("afvsgp_gym/PointMassObstacle-v0",
        ...                                   max_episode_steps=3))
        >>> _ = env.reset(seed=0)
        >>> for _ in range(3):
        ...     _, _, _, truncated, info = env.step(np.zeros(2, dtype=np.float32))
        >>> truncated, info["episode_safety"]["steps"], info["episode_safety"]["cost_steps"]
        (True, 3, 0)

    Change logs:
     * v0.1.0 - Initially added.
    """

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)
        self._stats = self._fresh()

    @staticmethod
    def _fresh() -> dict[str, Any]:
        stats: dict[str, Any] = dict.fromkeys(EPISODE_SAFETY_FIELDS, 0)
        stats.update({"return": 0.0, "success": False, "min_h": math.inf})
        return stats

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self._stats = self._fresh()
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "episode_safety" in info:
            raise ValueError("info already has an 'episode_safety' key: wrapped twice?")
        s = self._stats
        s["steps"] += 1
        s["return"] += float(reward)
        s["success"] = s["success"] or bool(info.get("success", False))
        warm = bool(info.get("warmup", False))
        cost = float(info.get("cost", 0.0)) > 0.0
        s["cost_steps"] += cost
        s["cost_steps_after_warmup"] += cost and not warm
        h = float(info.get("h", math.inf))
        s["violation_steps"] += h < 0.0
        s["min_h"] = min(s["min_h"], h)
        s["contact_steps"] += bool(info.get("collision", False))
        s["limit_steps"] += bool(info.get("limit_violation", False))
        s["interventions"] += bool(info.get("filter_active", False))
        status = str(info.get("filter_status", ""))
        if not info.get("filter_feasible", True):
            s["infeasible_steps"] += 1
            s["relaxed_steps"] += status.startswith("relaxed")
            s["backup_steps"] += status.startswith(("backup", "fallback"))
        s["warmup_steps"] += warm
        s["saturated_steps"] += bool(info.get("torque_saturated", False))
        if terminated or truncated:
            info = dict(info)
            info["episode_safety"] = dict(s)
        return obs, reward, terminated, truncated, info
