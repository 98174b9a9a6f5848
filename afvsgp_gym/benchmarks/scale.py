"""The learning's cost against the number of obstacles: per-pair learners against the shared one.

``python -m afvsgp_gym.benchmarks.scale [--quick] [--steps N] [--rounds R]`` runs the nominal
tracker behind ``SafetyFilter`` on the static Franka scenario with the kinematics known
(``nominal_model="kinematic"``, which the shared learner needs) and the 28 joint-limit
barriers, with the scenario's obstacle alone (21 arm spheres x 1 = 21 pairs) and with 24 more
spheres around the workspace (25 obstacles, 525 pairs), each behind the paper's per-barrier
learner (``"afvsgp"``: 21 or 525 pair learners and 7 joint learners) and the shared one
(``"afvsgp-shared"``: the 7 joint learners, every pair projected onto them; issue 45). The four
configurations advance in lockstep (:func:`afvsgp_gym.benchmarks.arm.time_lockstep`, whose
module docstring says what ``step``, ``learners``, ``update`` and ``env.step`` time), so their
ratios are measured on the same seconds. Pin the process to one core (``taskset -c 0``) with
``OPENBLAS_NUM_THREADS=1``. ``--crossover`` times the two learners at 1, 2, 3, 4 and 6
obstacles with the robot's own model as the prior: where the shared one becomes the faster;
``--defaults`` times ``SafetyFilter``'s default learner at 21 and 525 pairs with that prior.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import time_lockstep

#: the scenario's obstacle, then 24 spheres on three rings around the base (0.6-0.8 m out, at
#: three heights): the clutter of OSCBF's tabletop demo in number, mostly outside the
#: activation distance of the tracking arm, so the program stays small and the learning is
#: what grows
CLUTTER: list[dict[str, Any]] = [{"position": [0.307, 0.20, 0.417], "radius": 0.05}] + [
    {"position": [round(r * np.cos(a), 4), round(r * np.sin(a), 4), z], "radius": 0.04}
    for r, z in ((0.8, 0.15), (0.7, 0.55), (0.6, 0.95))
    for a in np.linspace(0.6, 2 * np.pi - 0.6, 8)
]

#: name -> configuration (:class:`afvsgp_gym.benchmarks.arm.TimedEpisode`'s spec)
CONFIGS: dict[str, dict[str, Any]] = {
    f"{pairs} pairs + 28 limits, {name}": {"learner": learner, "nominal_model": "kinematic",
                                           **kw}
    for pairs, kw in ((21, {}), (525, {"obstacles": CLUTTER}))
    for name, learner in (("per-pair learners", "afvsgp"), ("shared learner", "afvsgp-shared"))
}


def run(quick: bool = False, steps: int | None = None, rounds: int = 1,
        seed: int = 0) -> dict[str, float]:
    """Median and p99 (s) of the step, the learners and the update per configuration (pooled
    over ``rounds``), barriers in the program, and the ratios shared / per-pair."""
    steps = steps or (200 if quick else 1000)
    acc: dict[str, dict[str, list]] = {}
    for _ in range(1 if quick else rounds):
        for name, res in time_lockstep(CONFIGS, steps=steps, seed=seed).items():
            for k, v in res.items():
                acc.setdefault(name, {}).setdefault(k, []).append(v)
    out: dict[str, float] = {}
    for name, d in acc.items():
        for part in ("step", "learners", "update", "env_step"):
            x = np.concatenate(d[part])
            out[f"{name}: {part} median_s"] = float(np.median(x))
            out[f"{name}: {part} p99_s"] = float(np.percentile(x, 99))
        out[f"{name}: barriers in program (mean)"] = float(np.mean(np.concatenate(d["n_active"])))
    for k in ("21", "525"):
        per, shared = (f"{k} pairs + 28 limits, {w}" for w in ("per-pair learners",
                                                              "shared learner"))
        for part in ("step", "learners", "update", "env_step"):
            out[f"{k} pairs: {part} median, shared / per-pair"] = (
                out[f"{shared}: {part} median_s"] / out[f"{per}: {part} median_s"])
    return out


def defaults(steps: int = 1000, seed: int = 0) -> dict[str, float]:
    """``SafetyFilter``'s defaults (``learner="auto"``) with the robot's own model as the
    prior (``"perturbed"``): the step, the learning and the wrapped ``env.step`` (median and
    p99, s) at 21 and 525 pairs in lockstep, which learner the default took there (1: the
    shared one), and the ratios 525 / 21."""
    from afvsgp_gym.benchmarks.arm import TimedEpisode

    eps = {pairs: TimedEpisode({"learner": "auto", "nominal_model": "perturbed", **kw},
                               steps=steps, seed=seed)
           for pairs, kw in ((21, {}), (525, {"obstacles": CLUTTER}))}
    shared = {p: float(ep.env.learner_name == "afvsgp-shared") for p, ep in eps.items()}
    order = list(eps.values())
    while any(ep.remaining > 0 for ep in order):
        for ep in order:
            ep.step()
        order.reverse()
    out: dict[str, float] = {}
    for pairs, ep in eps.items():
        res, name = ep.result(), f"default, {pairs} pairs + 28 limits"
        out[f"{name}: shared learner"] = shared[pairs]
        for part in ("step", "learners", "env_step"):
            out[f"{name}: {part} median_s"] = float(np.median(res[part]))
            out[f"{name}: {part} p99_s"] = float(np.percentile(res[part], 99))
    for part in ("step", "env_step"):
        out[f"default: {part} median, 525 / 21 pairs"] = (
            out[f"default, 525 pairs + 28 limits: {part} median_s"]
            / out[f"default, 21 pairs + 28 limits: {part} median_s"])
    return out


#: obstacle counts of :func:`crossover`: the first of :data:`CLUTTER`'s spheres
CROSSOVER_OBSTACLES = (1, 2, 3, 4, 6)


def crossover(steps: int = 1500, seed: int = 0) -> dict[str, float]:
    """Where the shared learner's step becomes the faster: the filter's step (median, s)
    per learner with the first 1, 2, 3, 4 and 6 obstacles of :data:`CLUTTER` (21 pairs each)
    and the robot's own model as the prior (``"perturbed"``, where ``learner="auto"`` may
    take the shared learner, ``FrankaObstacleEnv.SHARED_LEARNER_PAIRS``), each count's two
    configurations in lockstep."""
    out: dict[str, float] = {}
    for n in CROSSOVER_OBSTACLES:
        specs = {name: {"learner": learner, "nominal_model": "perturbed",
                        "obstacles": CLUTTER[:n]}
                 for name, learner in (("per-pair", "afvsgp"), ("shared", "afvsgp-shared"))}
        res = time_lockstep(specs, steps=steps, seed=seed)
        for name, r in res.items():
            out[f"{21 * n} pairs, {name}: step median_s"] = float(np.median(r["step"]))
        out[f"{21 * n} pairs: step median, shared / per-pair"] = (
            out[f"{21 * n} pairs, shared: step median_s"]
            / out[f"{21 * n} pairs, per-pair: step median_s"])
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="200 steps, one round")
    p.add_argument("--steps", type=int, default=None, help="timed steps per episode")
    p.add_argument("--rounds", type=int, default=1, help="lockstep rounds")
    p.add_argument("--crossover", action="store_true",
                   help="the step per learner at 1, 2, 3, 4 and 6 obstacles instead")
    p.add_argument("--defaults", action="store_true",
                   help="SafetyFilter's default learner at 21 and 525 pairs, prior perturbed")
    args = p.parse_args(argv)
    print(machine())
    print(calibration_line(), flush=True)
    if args.crossover:
        results = crossover(200 if args.quick else args.steps or 1500)
    elif args.defaults:
        results = defaults(200 if args.quick else args.steps or 1000)
    else:
        results = run(args.quick, args.steps, args.rounds)
    for key, val in results.items():
        shown = f"{val * 1e6:10.1f} us" if key.endswith("_s") else f"{val:10.3f}"
        print(f"{key:70s} {shown}")


if __name__ == "__main__":
    main()
