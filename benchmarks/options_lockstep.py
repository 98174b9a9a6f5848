"""Filtered whole-arm step under several filter-option sets, their episodes run in lockstep.

On a VM whose speed drifts by tens of per cent over seconds, configurations timed one after
the other are not comparable. Here every option set gets its own env and filter (static
Franka scenario, 21 barriers, nominal "zero", AFVSGP, the nominal tracker), and the episodes
advance one control step each in turn inside one process, so drift hits all of them alike.
Per control step after warm-up it times ``SafetyController.filter`` + ``observe`` (as
``afvsgp_gym.benchmarks.arm`` does) and prints the median / p90 / p99 per seed and pooled,
and the ratios to the first option set.

    OPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/options_lockstep.py \\
        --seeds 0 1 2 3 4 5 6 7 8 9 --options '{}' '{"activation_distance": 0.1}'
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np

import afvsgp_gym  # noqa: F401  (registers the envs)
from afvsgp_gym.agents import NominalController
from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.cli import _json_arg, _positive
from afvsgp_gym.wrappers import SafetyFilter


class TimedEpisode:
    """One filtered episode whose controller's ``filter`` + ``observe`` are timed per step."""

    def __init__(self, options: dict, seed: int, env_id: str):
        self.env = SafetyFilter(gym.make(env_id), learner="afvsgp", seed=seed, **options)
        ctrl = self.env.controller
        self.times: list[float] = []
        filt, observe = ctrl.filter, ctrl.observe
        state = {"t": 0.0, "timed": False}

        def timed_filter(*a, **k):
            t0 = time.perf_counter()
            res = filt(*a, **k)
            state["t"] = time.perf_counter() - t0
            return res

        def timed_observe(*a, **k):
            t0 = time.perf_counter()
            z = observe(*a, **k)
            if state["timed"] and not ctrl.warming_up:
                self.times.append(state["t"] + time.perf_counter() - t0)
            state["timed"] = not ctrl.warming_up  # the first step after warm-up fits
            return z

        ctrl.filter, ctrl.observe = timed_filter, timed_observe
        self.policy = NominalController(self.env)
        self.obs, _ = self.env.reset(seed=seed)

    def step(self) -> None:
        self.obs, _, term, trunc, _ = self.env.step(self.policy(self.obs))
        if term or trunc:
            self.obs, _ = self.env.reset()


def _summary(t: np.ndarray) -> str:
    q = np.percentile(t, [50, 90, 99]) * 1e6
    return f"median {q[0]:7.0f}  p90 {q[1]:7.0f}  p99 {q[2]:7.0f} us"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--options", nargs="+", default=["{}"],
                   help="filter options per configuration, as JSON objects")
    p.add_argument("--steps", type=_positive, default=2000,
                   help="env steps per episode (the warm-up included)")
    p.add_argument("--env", default="afvsgp_gym/FrankaObstacleStatic-v0")
    args = p.parse_args(argv)
    options = [_json_arg(p, text, "--options") for text in args.options]
    print(machine())
    print(calibration_line(), flush=True)
    pooled: list[list[np.ndarray]] = [[] for _ in options]
    for seed in args.seeds:
        runs = [TimedEpisode(o, seed, args.env) for o in options]
        for _ in range(args.steps):
            for run in runs:
                run.step()
        for i, run in enumerate(runs):
            if not run.times:
                p.error(f"--steps {args.steps} ends before the warm-up does: nothing was timed")
            pooled[i].append(np.asarray(run.times))
            print(f"seed {seed:3d}  config {i}  {_summary(pooled[i][-1])}", flush=True)
            run.env.close()
    first = np.concatenate(pooled[0])
    for i, o in enumerate(options):
        t = np.concatenate(pooled[i])
        ratio = (f"  x config 0: median {np.median(t) / np.median(first):.3f}, p99 "
                 f"{np.percentile(t, 99) / np.percentile(first, 99):.3f}" if i else "")
        print(f"pooled config {i} {json.dumps(o)} ({t.size} steps): {_summary(t)}{ratio}")


if __name__ == "__main__":
    main()
