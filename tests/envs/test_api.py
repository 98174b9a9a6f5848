"""Gymnasium / SB3 checkers and vector envs for every registered afvsgp_gym id."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import afvsgp_gym  # noqa: F401

IDS = sorted(k for k in gym.registry if k.startswith("afvsgp_gym/"))


@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_check_env(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    gym_check_env(env.unwrapped, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_sb3_check_env(env_id):
    checker = pytest.importorskip(
        "stable_baselines3.common.env_checker", reason="needs the rl extra: pip install -e '.[rl]'"
    )
    env = gym.make(env_id)
    checker.check_env(env.unwrapped, warn=True)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("mode", ["sync", "async"])
def test_make_vec(env_id, mode):
    # forkserver: the EGL rendering of earlier tests leaves threads that fork() must not copy
    kwargs = {"context": "forkserver"} if mode == "async" else {}
    envs = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode, vector_kwargs=kwargs)
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (2, *envs.single_observation_space.shape)
    obs, r, term, trunc, info = envs.step(envs.action_space.sample())
    assert np.all(np.isfinite(obs)) and r.shape == (2,)
    assert "delta_b_true" in info and "cost" in info
    envs.close()
