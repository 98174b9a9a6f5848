"""Clarabel's own time on the filter's cone programs, with its settings varied.

Records every program the safety filter hands to clarabel in one whole-arm episode prefix
(``afvsgp_gym.benchmarks.arm.TimedEpisode``: static scenario, nominal "zero", AFVSGP, seed
``--seed``), then solves each again with :class:`~afvsgp_gym.cbf.cone_programs.ConePrograms`
(a reused solver per size, as in the filter) under each settings variant: the median time of
one update and solve, the median iterations, the time per iteration, the largest change of the
answer against the filter's settings and the statuses seen.

    OPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/clarabel_settings.py --seed 0
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import afvsgp_gym.cbf.cone_programs as cone_programs
from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import TimedEpisode

#: name -> clarabel settings changed on top of the filter's (``cone_programs.settings``)
VARIANTS: dict[str, dict] = {
    "filter's settings": {},
    "tolerance 1e-8": {"tol_gap_abs": 1e-8, "tol_gap_rel": 1e-8, "tol_feas": 1e-8},
    "tolerance 1e-7": {"tol_gap_abs": 1e-7, "tol_gap_rel": 1e-7, "tol_feas": 1e-7},
    "no iterative refinement": {"iterative_refinement_enable": False},
    "refinement 2 steps": {"iterative_refinement_max_iter": 2},
    "qdldl": {"direct_solve_method": "qdldl"},
    "faer": {"direct_solve_method": "faer"},
    "one thread": {"max_threads": 1},
}


def record_programs(seed: int, steps: int) -> tuple[np.ndarray, np.ndarray, list]:
    """``(low, high, programs)``: the ``(kind, u_nom, a0, a, G)`` clarabel solved in one episode."""
    ep = TimedEpisode({}, steps=steps, seed=seed)
    programs = ep.env.controller.socp.programs
    solve, out = programs.solve, []

    def recording(kind, u_nom, a0, a, G=None):
        out.append((kind, u_nom.copy(), a0.copy(), a.copy(), None if G is None else G.copy()))
        return solve(kind, u_nom, a0, a, G)

    programs.solve = recording
    while ep.remaining > 0:
        ep.step()
    low, high = programs.low.copy(), programs.high.copy()
    ep.result()
    return low, high, out


def time_variant(low, high, programs: list, changes: dict, tol: float, repeats: int = 3):
    """Median seconds per update-and-solve, median iterations, answers and statuses."""
    base = cone_programs.settings

    def patched(t, strictly_convex=False):
        s = base(t, strictly_convex)
        for key, val in changes.items():
            setattr(s, key, val)
        return s

    cone_programs.settings = patched
    try:
        progs = cone_programs.ConePrograms(low, high, tol, 1e-4)
        for kind, u_nom, a0, a, G in programs:
            progs.solve(kind, u_nom, a0, a, G)  # build the solvers
        times, iters, answers, statuses = [], [], [], set()
        for rep in range(repeats):
            for kind, u_nom, a0, a, G in programs:
                t0 = time.perf_counter()
                x, status = progs.solve(kind, u_nom, a0, a, G)
                times.append(time.perf_counter() - t0)
                if rep == 0:
                    answers.append(x[: low.size])
                    statuses.add(status)
                    iters.append(progs._solvers[(kind, a0.size)].solve().iterations)
    finally:
        cone_programs.settings = base
    return float(np.median(times)), float(np.median(iters)), np.array(answers), statuses


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=1500, help="timed steps of the episode")
    args = p.parse_args(argv)
    print(machine())
    print(calibration_line(), flush=True)
    low, high, programs = record_programs(args.seed, args.steps)
    sizes = np.bincount([a0.size for _, _, a0, _, _ in programs])
    print(f"{len(programs)} programs from seed {args.seed}; cones per program: "
          + ", ".join(f"{k}: {n}" for k, n in enumerate(sizes) if n))
    from afvsgp_gym.cbf.socp import SOCPFilter

    tol = SOCPFilter(low, high).tol
    ref = None
    print("variant                    solve (us)  iterations  us / iteration  max |du| vs "
          "filter's   statuses")
    for name, changes in VARIANTS.items():
        try:
            t, it, ans, statuses = time_variant(low, high, programs, changes, tol)
        except Exception as exc:  # a setting this clarabel does not know
            print(f"  {name:25s} failed: {type(exc).__name__}: {exc}")
            continue
        ref = ans if ref is None else ref
        print(f"  {name:25s} {t * 1e6:8.1f}   {it:8.1f}     {t * 1e6 / it:8.1f}       "
              f"{np.abs(ans - ref).max():.1e}          {sorted(statuses)}")


if __name__ == "__main__":
    main()
