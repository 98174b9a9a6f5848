"""A short PPO run with the safety filter in the loop (SB3 make_vec_env(wrapper_class=...))."""

import numpy as np
import pytest

sb3 = pytest.importorskip("stable_baselines3", reason="needs the rl extra: pip install -e '.[rl]'")

import afvsgp_gym  # noqa: E402,F401
from afvsgp_gym.wrappers import SafetyFilter  # noqa: E402


def test_ppo_trains_with_filter_in_the_loop():
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env

    class Record(BaseCallback):
        def __init__(self):
            super().__init__()
            self.infos = []

        def _on_step(self):
            self.infos.extend(self.locals["infos"])
            return True

    venv = make_vec_env(
        "afvsgp_gym/PointMassObstacle-v0",
        n_envs=2,
        seed=0,
        wrapper_class=SafetyFilter,
        wrapper_kwargs={"learner": "afvsgp", "learner_kwargs": {"num_inducing": 10}},
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    model = sb3.PPO("MlpPolicy", venv, n_steps=160, batch_size=80, n_epochs=2, seed=0, device="cpu")
    rec = Record()
    try:
        model.learn(total_timesteps=640, callback=rec)
    finally:
        torch.set_num_threads(threads)
    assert len(rec.infos) == 640
    for info in rec.infos:
        assert np.all(np.isfinite(info["action_applied"]))
        assert np.all(np.abs(info["action_applied"]) <= 1)
        assert "filter_feasible" in info and "delta_b_std" in info
    # both copies left warm-up (199 samples) and learn online
    for env in venv.envs:
        wrapper = env
        while not isinstance(wrapper, SafetyFilter):
            wrapper = wrapper.env
        assert not wrapper.controller.warming_up
        assert wrapper.controller.n_update_failures == 0
    assert any(not i["warmup"] for i in rec.infos)
    # A random initial policy could wander into an obstacle during warm-up, when the filter
    # has no model yet (nominal "zero"); once the learner is fitted no step may have cost.
    for k in range(2):
        mine = rec.infos[k::2]
        assert sum(i["warmup"] for i in mine) == 200  # the learner's warm-up samples
        assert [i["cost"] for i in mine if not i["warmup"]] == [0.0] * 120
    venv.close()
