"""Consistency of the obstacle estimator on the Franka scenarios' obstacles: the normalised
estimation error squared (NEES) of ``[p, v]`` per degree of freedom (1 for a consistent
filter, above for an overconfident one) and the mean velocity std, while the obstacle moves and
while it is still, per process noise and camera, over seeded dynamic and random scenes.

    python benchmarks/estimator_consistency.py  # writes results/estimator_consistency.json

It chose ``SafetyFilter``'s default ``estimator_process_std`` (the smallest value that is not
overconfident while the obstacles move); docs/perception.md shows the table.
"""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401
from afvsgp_gym.cbf.estimation import ObstacleEstimator

OUT = Path(__file__).resolve().parent / "results" / "estimator_consistency.json"
PROCESS_STDS = (0.01, 0.03, 0.1)
CAMERAS = ((0.01, 30.0, 0.06), (0.02, 30.0, 0.1), (0.01, 60.0, 0.03), (0.02, 250.0, 0.0))
SEEDS = range(6)


def run(process_std: float, noise: float, rate: float, delay: float) -> dict:
    acc = {"moving": [0.0, 0, []], "still": [0.0, 0, []]}
    for scene in ("Dynamic", "Random"):
        for seed in SEEDS:
            env = gym.make(f"afvsgp_gym/FrankaObstacle{scene}-v0", obstacle_noise=noise,
                           obstacle_rate=rate, obstacle_delay=delay)
            env.reset(seed=seed)
            base = env.unwrapped
            est = ObstacleEstimator(1, noise, process_std=process_std)
            for step in range(250, 4000, 2):  # after the first second's transient
                t = step * base.dt
                pos, sample_time = base._camera.reading(t, base.obstacles)
                est.update(pos, sample_time)
                p, v, _, cov = est.predict(t)
                true_p, true_v, _ = base.obstacles[0].state(t)
                err = np.stack([p[0] - true_p, v[0] - true_v])
                nees = float(np.einsum("ix,ij,jx->", err, np.linalg.inv(cov[0][:2, :2]), err))
                cell = acc["moving" if np.linalg.norm(true_v) > 0.02 else "still"]
                cell[0] += nees
                cell[1] += 6
                cell[2].append(float(np.sqrt(cov[0][1, 1])))
    return {k: {"nees_per_dof": v[0] / v[1], "velocity_std": float(np.mean(v[2]))}
            for k, v in acc.items() if v[1]}


def main() -> None:
    rows = [{"process_std": q, "noise": n, "rate": r, "delay": d, **run(q, n, r, d)}
            for q in PROCESS_STDS for n, r, d in CAMERAS]
    OUT.write_text(json.dumps({"rows": rows}, indent=1) + "\n", encoding="utf-8")
    for row in rows:
        print(row)


if __name__ == "__main__":
    main()
