"""The RL pipeline on the Franka reach task: train (SubprocVecEnv, filter in the loop, action
repeat) -> per-episode logs -> zip -> held-action policy -> evaluate, with tiny budgets."""

import csv
import json

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="needs the rl extra: pip install -e '.[rl]'")

import afvsgp_gym  # noqa: E402,F401
from afvsgp_gym.agents.sb3 import (  # noqa: E402
    EPISODE_LOG_FIELDS,
    HeldPolicy,
    load_policy,
    train,
)
from afvsgp_gym.cli import main  # noqa: E402

REACH = "afvsgp_gym/FrankaObstacleReach-v0"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """PPO behind the AFVSGP filter, two worker processes, episodes cut to 300 env steps."""
    out = tmp_path_factory.mktemp("reach")
    res = train("ppo", REACH, learner="afvsgp", timesteps=128, path=out / "agent",
                seed=0, n_envs=2, env_kwargs={"max_episode_steps": 300},
                algo_kwargs={"n_steps": 64, "batch_size": 32, "n_epochs": 1},
                log_dir=out / "logs")
    return res


def test_training_logs_every_episode(trained):
    res = trained
    assert res.path.suffix == ".zip" and res.path.is_file()
    assert res.timesteps == 128 and res.env_steps == 1280  # action repeat 10
    # 64 agent steps per worker = 640 env steps = two 300-step episodes each
    assert len(res.episodes) == 4
    with open(res.log_dir / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == EPISODE_LOG_FIELDS
    assert len(rows) == 4
    assert sorted(int(r["worker"]) for r in rows) == [0, 0, 1, 1]
    n_warm = gym.make(REACH).unwrapped.warmup_steps - 1  # SafetyFilter's warm-up samples
    for r in res.episodes:
        assert r["steps"] == 300
        # each worker's filter warms up once in its first episode, then learns
        assert r["warmup_steps"] in (0, n_warm)
        assert r["cost_steps_after_warmup"] <= r["cost_steps"]
        assert r["interventions"] >= r["infeasible_steps"] >= r["backup_steps"]
    assert sum(r["warmup_steps"] for r in res.episodes) == 2 * n_warm
    with open(res.log_dir / "progress.csv") as fh:
        progress = list(csv.DictReader(fh))
    assert "safety/cumulative_cost_steps" in progress[-1]
    assert "rollout/success_rate" in progress[-1]
    assert int(progress[-1]["safety/env_steps"]) == 1280


def test_zip_holds_actions_like_the_training_loop(trained):
    env = gym.make(REACH)
    policy = load_policy(trained.path, env=env)
    assert isinstance(policy, HeldPolicy)
    assert policy.action_repeat == 10
    assert policy.meta["learner"] == "afvsgp" and policy.meta["env_id"] == REACH
    obs, _ = env.reset(seed=0)
    actions, observations = [], []
    for _ in range(25):
        observations.append(obs)
        a = policy(obs)
        actions.append(a)
        obs, *_ = env.step(a)
    actions = np.array(actions)
    assert np.all(np.isfinite(actions)) and actions.shape == (25, 3)
    # new predictions only at calls 0, 10, 20, from the observation of that call: the held
    # action is what ActionRepeat applies in training
    for start in (0, 10, 20):
        want, _ = policy.model.predict(observations[start], deterministic=True)
        np.testing.assert_array_equal(actions[start:start + 10], np.tile(want, (len(
            actions[start:start + 10]), 1)))
    assert not np.all(actions[0] == actions[10])
    policy.reset()  # a new episode predicts at once
    np.testing.assert_array_equal(policy(observations[5]), policy.model.predict(
        observations[5], deterministic=True)[0])
    assert load_policy(trained.path, action_repeat=1).action_repeat == 1


def test_evaluate_runs_the_zip_at_once(trained, tmp_path, capsys):
    jpath = tmp_path / "r.json"
    assert main(["evaluate", "--env", REACH, "--agent", str(trained.path), "--learner",
                 "afvsgp", "--episodes", "1", "--max-steps", "120", "--json", str(jpath),
                 "--no-progress"]) == 0
    rec = json.loads(jpath.read_text())["episodes"][0]
    assert rec["steps"] == 120 and rec["learner"] == "afvsgp"
    capsys.readouterr()


def test_cli_train_unfiltered_prints_the_evaluate_command(tmp_path, capsys):
    zpath = tmp_path / "u.zip"
    assert main(["train", "--env", REACH, "--no-filter", "--timesteps", "64",
                 "--env-kwargs", '{"max_episode_steps": 200}',
                 "--algo-kwargs", '{"n_steps": 64, "batch_size": 32, "n_epochs": 1}',
                 "--out", str(zpath), "--log-dir", str(tmp_path / "logs")]) == 0
    out = capsys.readouterr().out
    assert "behind no filter" in out and "640 env steps" in out
    assert f"--agent {zpath}" in out
    assert (tmp_path / "logs" / "episodes.csv").is_file()
    assert load_policy(zpath).meta["learner"] is None


def test_train_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="action_repeat"):
        train("ppo", REACH, timesteps=10, action_repeat=0, path=tmp_path / "x")
    with pytest.raises(ValueError, match="algo"):
        train("dqn", REACH, timesteps=10, path=tmp_path / "x")
    with pytest.raises(SystemExit) as exc:
        main(["train", "--env", REACH, "--algo-kwargs", "[1]", "--out", str(tmp_path / "a.zip")])
    assert exc.value.code == 2
