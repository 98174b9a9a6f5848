"""Where the whole-arm step's time goes: by barriers in the cone program, and by solver path.

The episodes of ``afvsgp_gym.benchmarks.arm`` (static scenario, nominal "zero", AFVSGP at the
env's settings, the nominal tracker; 21 barriers unless ``--spheres ee``), one after another,
with the same per-step timers (``step`` = ``SafetyController.filter`` + ``observe``,
``filter`` alone) plus one around ``SOCPFilter.solve`` and one around clarabel's solves inside
it. Prints, per number of barriers in the program, the share of steps and the step / filter
times, a least-squares line ``filter = a + b n``, per solver outcome (inactive, a certified
fast path, clarabel) the share, the time of ``solve`` and the clarabel part of it, and per band
of step time (below the median, median-p90, p90-p99, the slowest 1 %) the mean of each part of
the step: the learners' update and predictions, ``solve`` and clarabel inside it, the
one-cone projection in numpy inside it (``fastpath.project_cone_box``: programs with one
cone, and the several-cones path's fallback) with the share of steps that ran it, the rest,
the share of steps with an inducing-set change and the solver outcomes.

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
    # the one-cone projection in numpy (fastpath.project_cone_box): programs with one cone,
    # and the several-cones path's fallback when the compiled search does not settle
    for name in ("_one_cone", "_project_one"):
        _timed(socp, name, record, "python_projection")


def _timed(obj, name: str, clock: dict, key: str) -> None:
    """Wrap ``obj.name`` to add its wall time to ``clock[key]``."""
    fn = getattr(obj, name)

    def wrapper(*a, **k):
        t0 = time.perf_counter()
        out = fn(*a, **k)
        clock[key] += time.perf_counter() - t0
        return out

    setattr(obj, name, wrapper)


def _parts(ep: TimedEpisode, record: dict, parts: dict) -> None:
    """Advance ``ep`` to its end, appending per timed step the update, prediction, solve and
    clarabel times (s), whether an inducing set changed and the solver outcome to ``parts``."""
    ctrl, clock, wrapped = ep.env.controller, {}, False
    while ep.remaining > 0:
        bank = getattr(ctrl.bank, "bank", None)
        if bank is not None and not wrapped:  # the stacked bank exists after the warm-up fit
            _timed(bank, "update", clock, "update")
            _timed(bank, "predict_affine", clock, "predict")
            wrapped = True
        changes = int(bank.n_added_.sum()) if bank is not None else 0
        clock.update(update=0.0, predict=0.0)
        record["python_projection"] = 0.0
        n_calls, n_timed = len(record["calls"]), len(ep.out["step"])
        ep.step()
        if len(ep.out["step"]) == n_timed:
            continue
        calls = record["calls"][n_calls:]
        parts["update"].append(clock["update"])
        parts["predict"].append(clock["predict"])
        parts["solve"].append(sum(c[1] for c in calls))
        parts["clarabel"].append(sum(c[3] for c in calls))
        parts["python_projection"].append(record["python_projection"])
        parts["inducing"].append(int(bank.n_added_.sum()) > changes)
        parts["outcome"].append(calls[-1][0] if calls else "none")


def _print_bands(step: np.ndarray, parts: dict) -> None:
    """Mean of each part of the step per band of step time (us)."""
    p = {k: np.asarray(v) for k, v in parts.items()}
    print("step band    steps   step  update  predict  solve  (clarabel)  (numpy cone: share)  "
          "rest   inducing change   outcomes")
    edges = np.percentile(step, [0, 50, 90, 99, 100])
    for name, lo, hi in zip(("<p50", "p50-p90", "p90-p99", ">p99"), edges[:-1], edges[1:],
                            strict=True):
        m = (step >= lo) & (step <= hi)
        upd, pred = p["update"][m] * 1e6, p["predict"][m] * 1e6
        sol, clar = p["solve"][m] * 1e6, p["clarabel"][m] * 1e6
        proj = p["python_projection"][m] * 1e6
        rest = step[m] - upd - pred - sol
        kinds = defaultdict(int)
        for k in p["outcome"][m]:
            kinds[k] += 1
        top = ", ".join(f"{k} {v / m.sum():.2f}" for k, v in
                        sorted(kinds.items(), key=lambda kv: -kv[1])[:3])
        print(f"  {name:9s} {m.sum():6d}  {step[m].mean():5.0f}  {upd.mean():6.0f}  "
              f"{pred.mean():7.0f}  {sol.mean():5.0f}  ({clar.mean():5.0f})    "
              f"({proj.mean():5.0f}: {(proj > 0).mean():.2f})       "
              f"{rest.mean():5.0f}  {p['inducing'][m].mean():.2f}              {top}")


def run(seeds, steps: int, spheres: str | None) -> None:
    spec = {} if spheres is None else {"safety_spheres": spheres}
    per_step = defaultdict(list)
    parts: dict = defaultdict(list)
    record: dict = {"calls": [], "python_projection": 0.0}
    for seed in seeds:
        ep = TimedEpisode(spec, steps=steps, seed=seed)
        _timed_solver(ep.env.controller.socp, record)
        _parts(ep, record, parts)
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
    _print_bands(step, parts)


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
