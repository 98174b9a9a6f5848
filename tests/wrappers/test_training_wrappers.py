"""ActionRepeat and EpisodeSafetyStats against hand-counted loops."""

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401
from afvsgp_gym.wrappers import ActionRepeat, EpisodeSafetyStats, SafetyFilter

PM = "afvsgp_gym/PointMassObstacle-v0"


def test_action_repeat_equals_the_inner_loop():
    """Each action held for `repeat` inner steps: same observations and summed rewards as
    stepping the inner env by hand; a shorter last step when the episode ends."""
    a = ActionRepeat(gym.make(PM, max_episode_steps=23), repeat=5)
    b = gym.make(PM, max_episode_steps=23)
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    rng = np.random.default_rng(0)
    taken = []
    while True:
        u = rng.uniform(-1, 1, 2).astype(np.float32)
        oa, ra, ta, tra, info = a.step(u)
        rb, inner = 0.0, 0
        while inner < 5:
            ob, r, tb, trb, _ = b.step(u)
            rb += r
            inner += 1
            if tb or trb:
                break
        taken.append(info["repeat_steps"])
        np.testing.assert_array_equal(oa, ob)
        assert ra == pytest.approx(rb, rel=1e-12, abs=1e-12)
        assert (ta, tra) == (tb, trb) and info["repeat_steps"] == inner
        if ta or tra:
            break
    assert taken == [5, 5, 5, 5, 3]
    with pytest.raises(ValueError, match="repeat"):
        ActionRepeat(gym.make(PM), repeat=0)


def test_episode_safety_stats_count_every_filtered_step():
    """Counts behind the filter and an action repeat equal those of the infos of every inner
    step (read by a recording wrapper placed at the same level)."""

    class Record(gym.Wrapper):
        def __init__(self, env):
            super().__init__(env)
            self.infos = []

        def step(self, action):
            out = self.env.step(action)
            self.infos.append(out[4])
            return out

    env = gym.make(PM, max_episode_steps=400, warmup_steps=60)
    rec = Record(SafetyFilter(env, learner="afvsgp", seed=0))
    wrapped = ActionRepeat(EpisodeSafetyStats(rec), repeat=4)
    wrapped.reset(seed=0)
    rng = np.random.default_rng(1)
    total = 0.0
    while True:
        _, r, term, trunc, info = wrapped.step(rng.uniform(-1, 1, 2).astype(np.float32))
        total += r
        if term or trunc:
            break
    stats = info["episode_safety"]
    infos = rec.infos
    assert stats["steps"] == len(infos) == 400
    assert stats["return"] == pytest.approx(total, rel=1e-12)
    assert stats["cost_steps"] == sum(i["cost"] > 0 for i in infos)
    assert stats["cost_steps_after_warmup"] == sum(i["cost"] > 0 and not i["warmup"]
                                                   for i in infos)
    assert stats["warmup_steps"] == sum(i["warmup"] for i in infos) > 0
    assert stats["interventions"] == sum(i["filter_active"] for i in infos) > 0
    assert stats["infeasible_steps"] == sum(not i["filter_feasible"] for i in infos)
    assert stats["relaxed_steps"] + stats["backup_steps"] <= stats["infeasible_steps"]
    assert stats["min_h"] == min(i["h"] for i in infos)
    assert stats["violation_steps"] == sum(i["h"] < 0 for i in infos)
    # a fresh episode starts from zero; a second stats wrapper on top is refused
    wrapped.reset(seed=1)
    _, _, _, _, info = wrapped.step(np.zeros(2, dtype=np.float32))
    assert "episode_safety" not in info
    double = EpisodeSafetyStats(EpisodeSafetyStats(gym.make(PM, max_episode_steps=1)))
    double.reset(seed=0)
    with pytest.raises(ValueError, match="episode_safety"):
        double.step(np.zeros(2, dtype=np.float32))


def test_episode_safety_stats_count_as_the_episode_runner():
    """EpisodeSafetyStats and the episode runner count with the one EpisodeCounter: the
    same episode (the runner stepping the stats wrapper) gives the same counts."""
    from afvsgp_gym.evaluation import make_policy, run_episode

    env = EpisodeSafetyStats(SafetyFilter(gym.make(PM, max_episode_steps=500), learner="afvsgp",
                                          seed=0))
    seen = []
    counts, _ = run_episode(env, make_policy("nominal", env), seed=0, on_step=seen.append)
    stats = seen[-1]["episode_safety"]
    assert counts["steps"] == stats["steps"] == 500
    for name in ("return", "cost_steps", "violation_steps", "contact_steps", "limit_steps",
                 "min_h", "interventions", "infeasible_steps"):
        assert counts[name] == stats[name], name
    assert stats["interventions"] > 0
