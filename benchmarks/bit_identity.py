"""Hashes of the observations of 5 filtered episodes: a check that a change keeps the
arithmetic (run before and after on one machine; equal hashes mean bit-identical episodes).

    python benchmarks/bit_identity.py [--steps 1500]

The episodes: static, dynamic with the kinematic prior, random (these three without the
self-collision barriers, as before they were the default), static with the end-effector
sphere, and static with today's defaults (self-collision on); AFVSGP behind the nominal
tracker, seeds 0-4.
"""

from __future__ import annotations

import argparse
import hashlib

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401  (registers the envs)
from afvsgp_gym.agents import NominalController
from afvsgp_gym.wrappers import SafetyFilter

CASES = (
    ("afvsgp_gym/FrankaObstacleStatic-v0", {"self_collision": False}),
    ("afvsgp_gym/FrankaObstacleDynamic-v0",
     {"nominal_model": "kinematic", "self_collision": False}),
    ("afvsgp_gym/FrankaObstacleRandom-v0", {"self_collision": False}),
    ("afvsgp_gym/FrankaObstacleStatic-v0", {"safety_spheres": "ee"}),
    ("afvsgp_gym/FrankaObstacleStatic-v0", {}),
)


def episode_hash(env_id: str, kwargs: dict, seed: int, steps: int) -> str:
    """The first 12 hex digits of the SHA-256 of every observation and reward."""
    env = SafetyFilter(gym.make(env_id, **kwargs), learner="afvsgp", seed=seed)
    policy = NominalController(env)
    obs, _ = env.reset(seed=seed)
    digest = hashlib.sha256()
    for _ in range(steps):
        obs, reward, term, trunc, _ = env.step(policy(obs))
        digest.update(np.ascontiguousarray(obs).tobytes())
        digest.update(np.float64(reward).tobytes())
        if term or trunc:
            obs, _ = env.reset()
    env.close()
    return digest.hexdigest()[:12]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1500)
    steps = parser.parse_args().steps
    for seed, (env_id, kwargs) in enumerate(CASES):
        print(env_id, kwargs, episode_hash(env_id, kwargs, seed, steps), flush=True)


if __name__ == "__main__":
    main()
