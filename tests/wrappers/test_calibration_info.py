"""The band's calibration through the wrapper: ``info["delta_b_lower"]`` and
``info["calibration"]`` step by step, their episode counts, the records and the summary."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import afvsgp_gym  # noqa: F401  (registers the envs)
from afvsgp_gym.episode_counts import EpisodeCounter
from afvsgp_gym.evaluation import run_episode, summarize
from afvsgp_gym.wrappers import SafetyFilter

KEYS = {"samples", "misses", "within_1std", "within_2std", "within_3std", "near_samples",
        "near_misses"}


@pytest.mark.parametrize("calibration", ["off", "conformal", "conformal-additive"])
def test_info_reports_the_band_and_the_counter_sums_it(calibration):
    env = SafetyFilter(gym.make("afvsgp_gym/PointMassObstacle-v0", max_episode_steps=600),
                       learner="afvsgp", calibration=calibration, warmup_samples=100)
    obs, _ = env.reset(seed=2)
    counter = EpisodeCounter()
    sums = dict.fromkeys(KEYS, 0)
    true_n = true_miss = 0
    rng = np.random.default_rng(0)
    for _ in range(600):
        action = rng.uniform(env.action_space.low, env.action_space.high)
        obs, reward, terminated, truncated, info = env.step(action.astype(np.float32))
        counter.update(reward, info)
        lower = info["delta_b_lower"]
        assert lower.shape == (env.unwrapped.n_barriers,)
        cal = info["calibration"]
        if info["warmup"]:
            assert cal is None
            continue
        if cal is None:  # no barrier predicted in this step
            assert np.isnan(lower).all()
            continue
        assert set(cal) == KEYS
        assert cal["samples"] == np.isfinite(lower).sum()
        assert 0 <= cal["misses"] <= cal["samples"]
        assert cal["within_1std"] <= cal["within_2std"] <= cal["within_3std"] <= cal["samples"]
        assert cal["near_misses"] <= cal["near_samples"] <= cal["samples"]
        for k in KEYS:
            sums[k] += cal[k]
        ok = np.isfinite(lower)
        true_n += int(ok.sum())
        true_miss += int((info["delta_b_true"][ok] < lower[ok]).sum())
        if terminated or truncated:
            break
    assert sums["samples"] > 100
    assert counter.calibration_samples == sums["samples"]
    assert counter.calibration_misses == sums["misses"]
    assert counter.calibration_within_2std == sums["within_2std"]
    assert counter.calibration_near_samples == sums["near_samples"]
    assert counter.calibration_near_misses == sums["near_misses"]
    assert (counter.true_band_samples, counter.true_band_misses) == (true_n, true_miss)


def test_records_and_summary_carry_the_rates():
    env = SafetyFilter(gym.make("afvsgp_gym/PointMassObstacle-v0", max_episode_steps=500),
                       learner="afvsgp", warmup_samples=100)
    rng = np.random.default_rng(1)

    def policy(_obs):
        return rng.uniform(-1.0, 1.0, 2).astype(np.float32)

    records = [run_episode(env, policy, seed)[0] for seed in (0, 1)]
    for r in records:
        assert r["calibration_samples"] > 0
        assert r["calibration_within_1std"] <= r["calibration_within_3std"]
        assert r["calibration_near_samples"] <= r["calibration_samples"]
        assert r["calibration_near_misses"] <= r["calibration_near_samples"]
    assert sum(r["calibration_near_samples"] for r in records) > 0  # seed 1 comes close
    s = summarize(records)
    n = sum(r["calibration_samples"] for r in records)
    assert s["calibration_samples"] == n
    assert s["miss_rate"] == sum(r["calibration_misses"] for r in records) / n
    assert s["coverage_2std"] == sum(r["calibration_within_2std"] for r in records) / n
    assert s["near_miss_rate"] == (sum(r["calibration_near_misses"] for r in records)
                                   / sum(r["calibration_near_samples"] for r in records))
    assert s["true_miss_rate"] == (sum(r["true_band_misses"] for r in records)
                                   / sum(r["true_band_samples"] for r in records))


def test_summary_of_records_without_calibration_fields():
    """Records of older sweeps (no calibration fields) summarize with NaN rates."""
    rec = {"steps": 10, "return": 0.0, "cost_steps": 0, "violation_steps": 0,
           "contact_steps": 0, "min_h": 0.1, "interventions": 0, "infeasible_steps": 0,
           "tracking_error_mean": 0.0, "tracking_error_max": 0.0, "unstable": False,
           "filter_time_median_s": 1e-4, "filter_time_p99_s": 2e-4}
    s = summarize([rec])
    assert s["calibration_samples"] == 0
    assert np.isnan(s["miss_rate"]) and np.isnan(s["coverage_1std"])


def test_miss_probability_replaces_beta_under_the_envs_suggestions():
    """The Franka envs suggest a conformal correction on the joint limits (the margin on the
    ranges, the multiplier on the speeds, the pairs off): a miss probability
    keeps it (a band to calibrate), ``0.5`` (``beta = 0``, no band) drops it, and both
    ``beta`` and ``miss_probability`` are refused."""
    from scipy.stats import norm

    franka = "afvsgp_gym/FrankaObstacleStatic-v0"
    env = SafetyFilter(gym.make(franka), learner="afvsgp", miss_probability=0.02)
    assert env.controller.config.beta == pytest.approx(norm.isf(0.02), rel=1e-10)
    modes = env.controller.config.calibration
    pairs = env.unwrapped.n_barriers - 28
    assert modes == ("off",) * pairs + ("conformal-additive",) * 14 + ("conformal",) * 14
    env.close()
    env = SafetyFilter(gym.make(franka), learner="afvsgp", miss_probability=0.5)
    assert env.controller.config.beta == 0.0 and env.controller.config.calibration == "off"
    env.close()
    with pytest.raises(ValueError, match="beta or miss_probability"):
        SafetyFilter(gym.make(franka), learner="afvsgp", beta=2.0, miss_probability=0.02)
