"""What noisy joint encoders do to the learners: AFVSGP behind the nominal tracker on the static
scene with ``velocity_noise`` (and a tenth of it as ``position_noise``), the eq. 48 samples then
differencing noisy joint speeds. Per setting: cost, backup steps, tracking, the learners'
noise standard deviations (obstacle pairs, joints) against the finite difference's own
``sqrt(2) sigma_v / dt``, and the band's miss rate.

    python benchmarks/encoder_noise.py   # writes benchmarks/results/encoder_noise.json
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401
from afvsgp_gym.evaluation import make_policy, run_episode
from afvsgp_gym.wrappers import SafetyFilter

OUT = Path(__file__).resolve().parent / "results" / "encoder_noise.json"
NOISES = (0.0, 0.01, 0.05)
SEEDS = (0, 1)


def main() -> None:
    rows = []
    for prior in ("zero", "perturbed"):
        for noise in NOISES:
            for seed in SEEDS:
                env = SafetyFilter(gym.make("afvsgp_gym/FrankaObstacleStatic-v0",
                                            nominal_model=prior, velocity_noise=noise,
                                            position_noise=noise / 10), learner="afvsgp")
                counts, _ = run_episode(env, make_policy("nominal", env, seed=seed), seed)
                base = env.unwrapped
                k = base.n_obstacle_barriers
                var = env.controller.bank.noise_variance(np.arange(base.n_barriers))
                rows.append({
                    "prior": prior, "velocity_noise": noise, "seed": seed,
                    "cost_steps": counts["cost_steps"], "min_h": counts["min_h"],
                    "backup_steps": counts["infeasible_steps"],
                    "tracking_error_mean": counts["tracking_error_mean"],
                    "pair_noise_std": float(np.sqrt(np.median(var[:k]))),
                    "joint_noise_std": float(np.sqrt(np.median(var[k:]))),
                    "difference_noise_std": math.sqrt(2.0) * noise / base.dt,
                    "miss_rate": counts["calibration_misses"]
                    / max(1, counts["calibration_samples"])})
                print(rows[-1])
    OUT.write_text(json.dumps({"rows": rows}, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
