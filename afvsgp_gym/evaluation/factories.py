"""The env and the agent of an episode, by name: :func:`make_env`, :func:`make_policy`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from afvsgp_gym.evaluation.spec import EpisodeSpec

__all__ = ["BUILTIN_AGENTS", "Policy", "make_env", "make_policy"]

#: Agents by name: the obstacle-blind tracker, uniform random actions and the adversarial
#: policies of :mod:`afvsgp_gym.agents.adversarial` (Franka torque envs).
BUILTIN_AGENTS = ("nominal", "random", "ram", *(f"swing{j}" for j in range(1, 8)), "greedy",
                  "untrained-ppo")

Policy = Callable[[np.ndarray], np.ndarray]


def make_policy(agent: str, env: Any, seed: int | None = None) -> Policy:
    """Build an ``obs -> action`` callable for ``agent``.

    ``"nominal"``: :class:`afvsgp_gym.agents.NominalController` (ignores obstacles, the filter's
    u_nom); ``"random"``: uniform samples of the action space seeded by ``seed``; ``"ram"``,
    ``"swing1"`` .. ``"swing7"``, ``"greedy"``, ``"untrained-ppo"``: the adversarial policies of
    :mod:`afvsgp_gym.agents.adversarial`; a path ending in ``.zip``: a Stable-Baselines3 model
    (deterministic actions, see :mod:`afvsgp_gym.agents.sb3`).
    """
    if agent == "nominal":
        from afvsgp_gym.agents import NominalController

        return NominalController(env)
    if agent == "random":
        space = env.action_space
        space.seed(seed)
        return lambda obs: space.sample()
    from afvsgp_gym.agents.adversarial import ADVERSARIAL_AGENTS

    if agent in ADVERSARIAL_AGENTS:
        return ADVERSARIAL_AGENTS[agent](env, seed=seed)
    if str(agent).endswith(".zip"):
        from afvsgp_gym.agents.sb3 import load_policy

        return load_policy(agent, env=env)
    raise ValueError(
        f"agent must be one of {', '.join(BUILTIN_AGENTS)} or a path to a Stable-Baselines3 "
        f".zip file, got {agent!r}"
    )


def make_env(spec: EpisodeSpec) -> Any:
    """A fresh env for ``spec``, behind ``SafetyFilter`` unless ``spec.learner`` is None."""
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401  (registers the ids)

    env = gym.make(spec.env_id, **dict(spec.env_kwargs))
    if spec.learner is None:
        return env
    from afvsgp_gym.wrappers import SafetyFilter

    fkw = {"seed": int(spec.seed), **dict(spec.filter_kwargs)}  # seeded exploration noise
    return SafetyFilter(env, learner=spec.learner, **fkw)
