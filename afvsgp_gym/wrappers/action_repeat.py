"""ActionRepeat: an agent acting every ``repeat`` steps of the wrapped env."""

from __future__ import annotations

import gymnasium as gym

from afvsgp_gym.validation import check_count

__all__ = ["ActionRepeat"]


class ActionRepeat(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Apply each action for ``repeat`` steps of the wrapped env (fewer if it ends first).

    Placed *outside* a :class:`~afvsgp_gym.wrappers.SafetyFilter`, the agent proposes an
    action at the lower rate while the filter still projects it at every step of the env
    (e.g. every 4 ms on the Franka envs), so each inner step is certified on its own state.

    The reward is the sum of the inner rewards; observation, ``terminated``, ``truncated`` and
    ``info`` are those of the last inner step, with ``info["repeat_steps"]`` the number of
    inner steps taken.

    Args:
        env: the environment.
        repeat: inner steps per action (>= 1).

    Example:
        >>> import gymnasium as gym
        >>> import numpy as np
        >>> import afvsgp_gym
        >>> env = ActionRepeat(gym.make("afvsgp_gym/PointMassObstacle-v0"), repeat=5)
        >>> _ = env.reset(seed=0)
        >>> _, _, _, _, info = env.step(np.zeros(2, dtype=np.float32))
        >>> info["repeat_steps"], round(info["time"] / env.unwrapped.dt)
        (5, 5)

    Change logs:
     * v0.1.0 - Initially added.
    """

    def __init__(self, env: gym.Env, repeat: int):
        self.repeat = check_count(repeat, "repeat")
        gym.utils.RecordConstructorArgs.__init__(self, repeat=self.repeat)
        gym.Wrapper.__init__(self, env)

    def step(self, action):
        total, steps = 0.0, 0
        while steps < self.repeat:
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            steps += 1
            if terminated or truncated:
                break
        info = dict(info)
        info["repeat_steps"] = steps
        return obs, total, terminated, truncated, info
