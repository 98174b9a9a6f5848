"""The filtered step against the number of obstacle primitives (issue 46's speed table).

``python -m afvsgp_gym.benchmarks.primitives [--quick] [--steps N] [--json PATH]`` runs the
nominal tracker behind ``SafetyFilter`` on the static Franka scenario whose obstacle is
replaced by ``obstacles=`` lists of 1, 4, 12 and 25 primitives: the table (a plane at the
mount), then boxes, capsules and spheres in turn on three rings around the base (0.6-0.8 m
out, mostly outside the activation distance of the tracking arm, as the tabletop's clutter
is), each list with the 21 arm spheres (21 pairs per primitive) and the 28 joint-limit
barriers; each behind the oracle (the true model) and AFVSGP with the robot's own model
(``nominal_model="perturbed"``, per-pair learners). The configurations advance in lockstep
(:func:`afvsgp_gym.benchmarks.arm.time_lockstep`, whose module docstring says what ``step``
and ``env.step`` time), so their ratios are measured on the same seconds. Pin the process to
one core (``taskset -c 0``) with ``OPENBLAS_NUM_THREADS=1``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import time_lockstep

#: numbers of primitives timed
COUNTS = (1, 4, 12, 25)
_KINDS = ("box", "capsule", "sphere")


def ring_primitives(n: int) -> list[dict[str, Any]]:
    """``n`` obstacle dicts: the table (a plane at the mount), then boxes, capsules and spheres
    in turn on three rings around the base (radii 0.8, 0.7, 0.6 m at heights 0.15, 0.55,
    0.95 m, eight places each), each about 5-8 cm in size."""
    out: list[dict[str, Any]] = [{"type": "plane", "position": [0.0, 0.0, 0.0],
                                  "normal": [0.0, 0.0, 1.0]}]
    places = [(r * np.cos(a), r * np.sin(a), z)
              for r, z in ((0.8, 0.15), (0.7, 0.55), (0.6, 0.95))
              for a in np.linspace(0.6, 2 * np.pi - 0.6, 8)]
    for i in range(n - 1):
        pos = [round(float(x), 4) for x in places[i % len(places)]]
        kind = _KINDS[i % 3]
        if kind == "box":
            out.append({"type": "box", "position": pos, "half_sizes": [0.05, 0.04, 0.06]})
        elif kind == "capsule":
            out.append({"type": "capsule", "position": pos, "radius": 0.03,
                        "half_length": 0.08, "axis": [0.0, 1.0, 0.0]})
        else:
            out.append({"type": "sphere", "position": pos, "radius": 0.05})
    return out


def configs() -> dict[str, dict[str, Any]]:
    """name -> :class:`~afvsgp_gym.benchmarks.arm.TimedEpisode` spec."""
    out: dict[str, dict[str, Any]] = {}
    for n in COUNTS:
        for name, learner, model in (("oracle", "oracle", "exact"),
                                     ("AFVSGP", "afvsgp", "perturbed")):
            out[f"{n} primitives, {name}"] = {"learner": learner, "nominal_model": model,
                                              "obstacles": ring_primitives(n)}
    return out


def run(quick: bool = False, steps: int | None = None, seed: int = 0) -> dict[str, Any]:
    """Per configuration: barriers, barriers in the program (mean), and the median and p99
    (s) of the filter's step (filter + learning) and of the wrapped ``env.step``."""
    steps = steps or (200 if quick else 1000)
    rows = []
    for name, res in time_lockstep(configs(), steps=steps, seed=seed).items():
        n, filt = name.split(" primitives, ")
        rows.append({
            "primitives": int(n), "filter": filt, "barriers": int(res["n_barriers"][0]),
            "in_program": float(np.mean(res["n_active"])),
            "step_median_s": float(np.median(res["step"])),
            "step_p99_s": float(np.percentile(res["step"], 99)),
            "env_step_median_s": float(np.median(res["env_step"])),
            "env_step_p99_s": float(np.percentile(res["env_step"], 99)),
        })
    return {"machine": machine(), "calibration": calibration_line(),
            "date": time.strftime("%Y-%m-%d"), "steps": steps, "rows": rows}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="200 steps")
    p.add_argument("--steps", type=int, default=None, help="timed steps per configuration")
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    args = p.parse_args(argv)
    out = run(args.quick, args.steps)
    print(out["machine"])
    print(out["calibration"])
    for r in out["rows"]:
        print(f"{r['primitives']:3d} primitives {r['filter']:7s} K={r['barriers']:4d} "
              f"in program {r['in_program']:6.1f}  step {1e6 * r['step_median_s']:7.0f} / "
              f"{1e6 * r['step_p99_s']:7.0f} us  env.step {1e6 * r['env_step_median_s']:7.0f}"
              f" / {1e6 * r['env_step_p99_s']:7.0f} us")
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
