"""Gymnasium registration of the afvsgp_gym environment ids (owned by the envs issue)."""

from __future__ import annotations

import gymnasium as gym


def register_envs() -> None:
    """Register every ``afvsgp_gym/*`` id once; safe to call repeatedly."""
    specs = {
        "afvsgp_gym/PointMassObstacle-v0": dict(
            entry_point="afvsgp_gym.envs.point_mass:PointMassObstacleEnv",
            max_episode_steps=1500,
        ),
    }
    for env_id, kwargs in specs.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, **kwargs)
