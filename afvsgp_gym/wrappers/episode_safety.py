"""EpisodeSafetyStats: per-episode safety and filter counts, at every step of the env."""

from __future__ import annotations

import gymnasium as gym

from afvsgp_gym.episode_counts import CALIBRATION_FIELDS, EpisodeCounter

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
    "self_contact_steps",
    "limit_steps",
    "min_h",
    "interventions",
    "infeasible_steps",
    "backup_steps",
    "relaxed_steps",
    "warmup_steps",
    "saturated_steps",
    "learner_error_steps",
    *CALIBRATION_FIELDS,
)


class EpisodeSafetyStats(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Count, over every step of an episode, what the safety report needs; at the episode's
    last step ``info["episode_safety"]`` holds the counts (keys :data:`EPISODE_SAFETY_FIELDS`).

    Place it between a :class:`~afvsgp_gym.wrappers.SafetyFilter` (or the bare env) and an
    :class:`~afvsgp_gym.wrappers.ActionRepeat`, so every filtered step is counted even when the
    agent acts less often.

    The counts are :class:`~afvsgp_gym.episode_counts.EpisodeCounter`'s (the episode runner's):

    - ``cost_steps``: ``info["cost"] > 0``
      (:data:`~afvsgp_gym.episode_counts.COST_DEFINITION`); ``cost_steps_after_warmup`` those with
      ``info["warmup"]`` False (the filter's learners fitted; every step without a filter);
      ``violation_steps`` h < 0; ``contact_steps`` ``info["collision"]``;
      ``self_contact_steps`` ``info["self_contact"]`` (the Franka envs: the arm touching
      itself or its base, a cost since their ``COST_VERSION`` 1); ``limit_steps``
      ``info["limit_violation"]``; ``min_h`` the smallest h.
    - ``interventions``: ``info["filter_active"]``; ``infeasible_steps`` not
      ``info["filter_feasible"]``, split by ``info["filter_status"]`` into ``backup_steps``
      (the backup or max-margin fallback applied) and ``relaxed_steps`` (the mean-only
      solution applied); ``warmup_steps`` with ``info["warmup"]``.
    - ``success``: some step had ``info["success"]``; ``saturated_steps``:
      ``info["torque_saturated"]``; ``learner_error_steps``: ``info["learner_error"]`` not
      None (a learner failed, the filter went on).
    - ``calibration_*`` and ``true_band_*``: the learned band's misses and coverages against
      the eq. 48 samples and against the exact model error (``info["calibration"]``,
      ``info["delta_b_lower"]``, ``info["delta_b_true"]``).

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
        self._counter = EpisodeCounter()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self._counter.reset()
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "episode_safety" in info:
            raise ValueError("info already has an 'episode_safety' key: wrapped twice?")
        self._counter.update(reward, info)
        if terminated or truncated:
            c = self._counter
            info = dict(info)
            info["episode_safety"] = {
                name: c.return_ if name == "return" else getattr(c, name)
                for name in EPISODE_SAFETY_FIELDS}
        return obs, reward, terminated, truncated, info
