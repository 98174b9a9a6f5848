"""train -> zip -> evaluate --agent zip round trip (tiny budgets)."""

import json

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.agents.sb3 import load_policy, train
from afvsgp_gym.cli import main

pytest.importorskip("stable_baselines3", reason="needs the rl extra: pip install -e '.[rl]'")

PM = "afvsgp_gym/PointMassObstacle-v0"


def test_train_then_evaluate_zip(tmp_path, capsys):
    zpath = tmp_path / "ppo_pm.zip"
    assert main(["train", "--algo", "ppo", "--env", PM, "--learner", "none", "--timesteps",
                 "128", "--out", str(zpath)]) == 0
    assert zpath.is_file()
    assert "saved" in capsys.readouterr().out
    jpath = tmp_path / "r.json"
    assert main(["evaluate", "--env", PM, "--agent", str(zpath), "--learner", "none",
                 "--episodes", "1", "--max-steps", "25", "--json", str(jpath),
                 "--no-progress"]) == 0
    rec = json.loads(jpath.read_text())["episodes"][0]
    assert rec["steps"] == 25
    # the same zip on an env with other spaces is refused before the run
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--env", "afvsgp_gym/FrankaObstacleStatic-v0", "--agent", str(zpath),
              "--learner", "none", "--episodes", "1000", "--no-progress"])
    assert exc.value.code == 2
    assert "observation_space" in capsys.readouterr().err
    policy = load_policy(zpath)
    env = gym.make(PM)
    obs, _ = env.reset(seed=0)
    a = policy(obs)
    assert a.shape == env.action_space.shape and np.all(np.isfinite(a))


def test_sac_with_filter_logs_cost(tmp_path):
    """Every finished training episode is logged with its cost: 40 agent steps of 10-step
    episodes (one env step per action here) are 4 episodes, and the oracle filter keeps
    them free of cost from the first step (no warm-up keeps the obstacle away)."""
    res = train("sac", PM, learner="oracle", timesteps=40, path=tmp_path / "sac",
                env_kwargs={"warmup_steps": 0, "max_episode_steps": 10},
                algo_kwargs={"learning_starts": 20, "batch_size": 16,
                             "policy_kwargs": {"net_arch": [16]}})
    assert res.path.suffix == ".zip" and res.path.is_file()
    assert load_policy(res.path).model.__class__.__name__ == "SAC"
    assert (res.timesteps, res.env_steps) == (40, 40)
    assert [r["steps"] for r in res.episodes] == [10] * 4
    assert [r["timesteps"] for r in res.episodes] == [10, 20, 30, 40]
    assert res.episode_costs == [0.0] * 4
    assert res.episode_interventions == [r["interventions"] for r in res.episodes]
