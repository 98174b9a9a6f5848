"""Where the whole-arm step's time goes: by barriers in the cone program, and by solver path.

The episodes of ``afvsgp_gym.benchmarks.arm`` (static scenario, nominal "zero", AFVSGP at the
env's settings, the nominal tracker; 21 barriers unless ``--spheres ee``), one after another,
with the same per-step timers (``step`` = ``SafetyController.filter`` + ``observe``,
``filter`` alone) plus one around ``SOCPFilter.solve`` and one around clarabel's solves inside
it. Prints, per number of barriers in the program, the share of steps and the step / filter
times, a least-squares line ``filter = a + b n``, and per solver outcome (inactive, a certified
fast path, clarabel) the share, the time of ``solve`` and the clarabel part of it.

    OPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/step_anatomy.py --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np

from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import TimedEpisode


def _timed_solver(socp, record: dict) -> None:
    """Wrap ``socp.solve`` (and clarabel's solves inside it) to append ``(status, total s,
    constraints, clarabel s)`` per call to ``record["calls"]``."""
    solve, programs_solve = socp.solve, socp.programs.solve
    inner = {"t": 0.0}

    def timed_programs(*a, **k):
        t0 = time.perf_counter()
        out = programs_solve(*a, **k)
        inner["t"] += time.perf_counter() - t0
        return out

    def timed_solve(u_nom, a0, *a, **k):
        inner["t"] = 0.0
        t0 = time.perf_counter()
        res = solve(u_nom, a0, *a, **k)
        total = time.perf_counter() - t0
        kind = res.status if res.status.startswith("certified") else res.status.split(":")[0]
        record["calls"].append((kind, total, np.size(a0), inner["t"]))
        return res

    socp.programs.solve, socp.solve = timed_programs, timed_solve


def run(seeds, steps: int, spheres: str | None) -> None:
    spec = {} if spheres is None else {"safety_spheres": spheres}
    per_step = defaultdict(list)
    record: dict = {"calls": []}
    for seed in seeds:
        ep = TimedEpisode(spec, steps=steps, seed=seed)
        _timed_solver(ep.env.controller.socp, record)
        while ep.remaining > 0:
            ep.step()
        for key, val in ep.result().items():
            per_step[key].append(val)
    r = {k: np.concatenate(v) for k, v in per_step.items()}
    n, step, filt = r["n_active"], r["step"] * 1e6, r["filter"] * 1e6
    print(f"{len(n)} timed steps, seeds {list(seeds)}; times in us (median / p99)")
    print("barriers in program   share    step            filter")
    for v in np.unique(n):
        m = n == v
        if m.sum() >= 20:
            print(f"  {int(v):2d}                  {m.mean():.3f}    "
                  f"{np.median(step[m]):5.0f} / {np.percentile(step[m], 99):5.0f}   "
                  f"{np.median(filt[m]):5.0f} / {np.percentile(filt[m], 99):5.0f}")
    a, b = np.linalg.lstsq(np.c_[np.ones(len(n)), n], filt, rcond=None)[0]
    print(f"filter ~ {a:.0f} + {b:.0f} us per barrier in the program (least squares)")
    print(f"all steps: step {np.median(step):.0f} / {np.percentile(step, 99):.0f}, "
          f"filter {np.median(filt):.0f} / {np.percentile(filt, 99):.0f}")
    calls = record["calls"]  # warm-up steps included: they are the quick "inactive" ones
    print("solver outcome (all calls)   share   solve median / mean / p99   "
          "constraints   clarabel mean")
    by_kind = defaultdict(list)
    for kind, total, k, clar in calls:
        by_kind[kind].append((total, k, clar))
    for kind, rows in sorted(by_kind.items(), key=lambda kv: -len(kv[1])):
        x = np.array(rows)
        t = x[:, 0] * 1e6
        print(f"  {kind:26s} {len(rows) / len(calls):.3f}   {np.median(t):5.0f} / "
              f"{t.mean():5.0f} / {np.percentile(t, 99):5.0f}        {x[:, 1].mean():4.1f}"
              f"        {x[:, 2].mean() * 1e6:5.0f}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=1500, help="timed steps per episode")
    p.add_argument("--spheres", choices=["ee"], default=None,
                   help="the end-effector sphere instead of the whole arm")
    args = p.parse_args(argv)
    print(machine())
    print(calibration_line(), flush=True)
    run(tuple(args.seeds), args.steps, args.spheres)


if __name__ == "__main__":
    main()
