"""Filtered whole-arm step under several filter-option sets, their episodes run in lockstep.

On a VM whose speed drifts by tens of per cent over seconds, configurations timed one after
the other are not comparable. Here every option set gets its own env and filter (static
Franka scenario, 21 barriers, nominal "zero", AFVSGP, the nominal tracker), and the episodes
advance one control step each in turn inside one process, so drift hits all of them alike
(``afvsgp_gym.benchmarks.arm.time_lockstep``, with its per-step timers of
``SafetyController.filter`` + ``observe``). Prints the median / p90 / p99 per seed and pooled,
and the ratios to the first option set.

    OPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/options_lockstep.py \\
        --seeds 0 1 2 3 4 5 6 7 8 9 --options '{}' '{"activation_distance": 0.1}'
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import ENV_ID, time_lockstep
from afvsgp_gym.cli import _json_arg, _positive


def _summary(t: np.ndarray) -> str:
    q = np.percentile(t, [50, 90, 99]) * 1e6
    return f"median {q[0]:7.0f}  p90 {q[1]:7.0f}  p99 {q[2]:7.0f} us"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--options", nargs="+", default=["{}"],
                   help="filter options per configuration, as JSON objects")
    p.add_argument("--steps", type=_positive, default=1500,
                   help="control steps per episode after the env's warmup_steps (timed from "
                        "the learners' warm-up fit on)")
    p.add_argument("--env", default=ENV_ID)
    args = p.parse_args(argv)
    options = [_json_arg(p, text, "--options") for text in args.options]
    print(machine())
    print(calibration_line(), flush=True)
    pooled: list[list[np.ndarray]] = [[] for _ in options]
    specs = {i: {"filter": o} for i, o in enumerate(options)}
    for seed in args.seeds:
        res = time_lockstep(specs, steps=args.steps, seed=seed, env_id=args.env)
        for i in specs:
            if not res[i]["step"].size:
                p.error(f"--steps {args.steps}: nothing was timed (the learners' warm-up "
                        f"did not end)")
            pooled[i].append(res[i]["step"])
            print(f"seed {seed:3d}  config {i}  {_summary(pooled[i][-1])}", flush=True)
    first = np.concatenate(pooled[0])
    for i, o in enumerate(options):
        t = np.concatenate(pooled[i])
        ratio = (f"  x config 0: median {np.median(t) / np.median(first):.3f}, p99 "
                 f"{np.percentile(t, 99) / np.percentile(first, 99):.3f}" if i else "")
        print(f"pooled config {i} {json.dumps(o)} ({t.size} steps): {_summary(t)}{ratio}")


if __name__ == "__main__":
    main()
