"""Gymnasium registration of the afvsgp_gym environment ids (owned by the envs issue)."""

from __future__ import annotations

import gymnasium as gym


def register_envs() -> None:
    """Register every ``afvsgp_gym/*`` id once; safe to call repeatedly."""
    franka = "afvsgp_gym.envs.franka:FrankaObstacleEnv"
    specs = {
        "afvsgp_gym/FrankaObstacleStatic-v0": dict(
            entry_point=franka, max_episode_steps=4000, kwargs={"scenario": "static"}
        ),
        "afvsgp_gym/FrankaObstacleDynamic-v0": dict(
            entry_point=franka, max_episode_steps=4000, kwargs={"scenario": "dynamic"}
        ),
        "afvsgp_gym/FrankaObstacleRandom-v0": dict(
            entry_point=franka, max_episode_steps=4000, kwargs={"scenario": "random"}
        ),
        "afvsgp_gym/FrankaTabletop-v0": dict(
            entry_point=franka, max_episode_steps=4000,
            kwargs={"scenario": "tabletop", "self_collision": True},
        ),
        "afvsgp_gym/FrankaShelf-v0": dict(
            entry_point=franka, max_episode_steps=4000,
            kwargs={"scenario": "shelf", "self_collision": True},
        ),
        "afvsgp_gym/FrankaObstacleReach-v0": dict(
            entry_point="afvsgp_gym.envs.reach:FrankaObstacleReachEnv", max_episode_steps=1250
        ),
        "afvsgp_gym/PointMassObstacle-v0": dict(
            entry_point="afvsgp_gym.envs.point_mass:PointMassObstacleEnv",
            max_episode_steps=1500,
        ),
    }
    for env_id, kwargs in specs.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, **kwargs)
