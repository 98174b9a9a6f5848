"""The filter's cone program on recorded programs: the fast path against a 40-digit
reference, and another ``socp.py`` timed against this one (tools kept out of the installed
package; ``afvsgp-gym bench`` runs the solver benchmark itself, ``afvsgp_gym.benchmarks.solver``).

:func:`record_filter_instances` records ``(u_nom, a0, a, G)`` of every cone program a
:class:`~afvsgp_gym.wrappers.SafetyFilter` solves on a registered env;
:func:`fast_path_agreement` compares the fast path with clarabel and with clarabel's answer
refined in 40-digit arithmetic (:func:`refine_kkt_mp`) on them; :func:`solver_before_after`
times another ``SOCPFilter`` module against this one on the calls of one episode. Command
line (from the repository's root; ``mpmath`` comes with the test extra)::

    python benchmarks/solver_instances.py --record N [--instances file.npz]
    python benchmarks/solver_instances.py --before path/to/other/socp.py
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from afvsgp_gym.benchmarks.solver import _stats
from afvsgp_gym.cbf import SOCPFilter

__all__ = ["fast_path_agreement", "load_instances", "main", "record_filter_instances",
           "refine_kkt_mp", "save_instances", "solver_before_after"]


def record_filter_instances(
    env_id: str = "afvsgp_gym/FrankaObstacleStatic-v0",
    n: int = 1000,
    learner: str = "afvsgp",
    seeds=range(1000),
    env_kwargs: dict | None = None,
    active_only: bool = True,
    **filter_options,
) -> list[tuple]:
    """Run seeded episodes of ``SafetyFilter(gym.make(env_id), learner)`` with the nominal
    tracker and record ``(u_nom, a0, a, G)`` of every ``SOCPFilter.solve`` call after
    warm-up (``active_only``: only those whose clipped proposal is unsafe, i.e. where a
    program is solved) until ``n`` are collected. Works with any controller that filters
    through ``controller.socp.solve``."""
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401
    from afvsgp_gym.agents import NominalController
    from afvsgp_gym.wrappers import SafetyFilter

    out: list[tuple] = []
    for seed in seeds:
        env = SafetyFilter(gym.make(env_id, **(env_kwargs or {})), learner=learner, seed=seed,
                           **filter_options)
        ctrl = env.controller
        socp = ctrl.socp
        inner = socp.solve  # the controller calls self.socp.solve: record around it

        def recording_solve(u_nom, a0, a, G=None, backup=None, _inner=inner, _ctrl=ctrl):
            res = _inner(u_nom, a0, a, G, backup)
            if not _ctrl.warming_up and not (active_only and res.status == "inactive"):
                out.append(tuple(None if x is None else np.array(x, dtype=np.float64)
                                 for x in (u_nom, a0, a, G)))
            return res

        socp.solve = recording_solve
        policy = NominalController(env)
        obs, _ = env.reset(seed=int(seed))
        try:
            while len(out) < n:
                obs, _, term, trunc, _ = env.step(policy(obs))
                if term or trunc:
                    break
        finally:
            env.close()
        if len(out) >= n:
            break
    return out[:n]


def save_instances(path, instances) -> None:
    """Save recorded ``(u_nom, a0, a, G)`` instances (any k per instance) to an ``.npz``."""
    ks = np.array([len(x[1]) for x in instances])
    m = len(instances[0][0])
    has_g = np.array([x[3] is not None for x in instances])
    G = [x[3] if x[3] is not None else np.zeros((len(x[1]), m + 1, m + 1)) for x in instances]
    np.savez_compressed(
        path, k=ks, has_g=has_g, u_nom=np.array([x[0] for x in instances]),
        a0=np.concatenate([x[1] for x in instances]),
        a=np.concatenate([x[2] for x in instances]).reshape(-1, m),
        G=np.concatenate(G).reshape(-1, m + 1, m + 1),
    )


def load_instances(path) -> list[tuple]:
    """Inverse of :func:`save_instances`."""
    with np.load(path) as z:
        d = {key: z[key] for key in z.files}  # decompress each array once
    idx = np.concatenate([[0], np.cumsum(d["k"])])
    return [
        (d["u_nom"][j], d["a0"][idx[j]:idx[j + 1]], d["a"][idx[j]:idx[j + 1]],
         d["G"][idx[j]:idx[j + 1]] if d["has_g"][j] else None)
        for j in range(len(d["k"]))
    ]


def refine_kkt_mp(u_guess, u_nom, a0, a, G, low, high, digits: int = 40, tol: float = 1e-7):
    """The program's optimum in ``digits``-digit arithmetic (mpmath), by Newton's method on
    the KKT equations with the active set read off ``u_guess`` (a clarabel answer: box faces
    within ``tol`` of ``u_guess``, constraints with margin below ``tol``); None unless the
    refined point satisfies every KKT condition (feasible, multipliers of the right sign).
    An independent high-precision reference for the fast path (it never sees its answer)."""
    import mpmath

    mp = mpmath.mp
    mp.dps = digits
    m, k = len(u_nom), len(a0)
    f = lambda x: [mp.mpf(float(v)) for v in np.ravel(x)]  # noqa: E731
    un, lo, hi, b0 = f(u_nom), f(low), f(high), f(a0)
    A = [f(row) for row in a]
    Gm = None if G is None else [[f(row) for row in Gi] for Gi in G]

    def cons(u, i):
        """c_i(u), grad, -Hessian (matrix) in mp."""
        c = b0[i] + mp.fsum(A[i][j] * u[j] for j in range(m))
        if Gm is None:
            return c, list(A[i]), mp.zeros(m, m)
        v = [Gm[i][r][0] + mp.fsum(Gm[i][r][j + 1] * u[j] for j in range(m))
             for r in range(m + 1)]
        nv = mp.sqrt(mp.fsum(x * x for x in v))
        if nv == 0:
            return c, None, None
        n = [x / nv for x in v]
        G1n = [mp.fsum(Gm[i][r][j + 1] * n[r] for r in range(m + 1)) for j in range(m)]
        grad = [A[i][j] - G1n[j] for j in range(m)]
        H = mp.zeros(m, m)
        for j in range(m):
            for l_ in range(m):
                gg = mp.fsum(Gm[i][r][j + 1] * Gm[i][r][l_ + 1] for r in range(m + 1))
                H[j, l_] = (gg - G1n[j] * G1n[l_]) / nv
        return c - nv, grad, H

    ug = np.asarray(u_guess, dtype=np.float64)
    at_lo = [abs(float(ug[j] - low[j])) <= tol for j in range(m)]
    at_hi = [abs(float(ug[j] - high[j])) <= tol for j in range(m)]
    free = [j for j in range(m) if not (at_lo[j] or at_hi[j])]
    u = [lo[j] if at_lo[j] else hi[j] if at_hi[j] else mp.mpf(float(ug[j])) for j in range(m)]
    act = [i for i in range(k) if float(cons(u, i)[0]) <= tol * (1 + abs(float(a0[i])))]
    lam = [mp.mpf(0)] * len(act)
    nF, nA = len(free), len(act)
    for _ in range(60):
        cs = [cons(u, i) for i in act]
        if any(c[1] is None for c in cs):
            return None
        res = [u[j] - un[j] - mp.fsum(lam[q] * cs[q][1][j] for q in range(nA)) for j in free]
        res += [c[0] for c in cs]
        if max((abs(x) for x in res), default=mp.mpf(0)) < mp.mpf(10) ** (-digits + 8):
            break
        J = mp.zeros(nF + nA, nF + nA)
        for r, j in enumerate(free):
            for cidx, l_ in enumerate(free):
                J[r, cidx] = (1 if j == l_ else 0) + mp.fsum(lam[q] * cs[q][2][j, l_]
                                                             for q in range(nA))
            for q in range(nA):
                J[r, nF + q] = -cs[q][1][j]
        for q in range(nA):
            for cidx, l_ in enumerate(free):
                J[nF + q, cidx] = cs[q][1][l_]
        try:
            step = mp.lu_solve(J, mp.matrix([-x for x in res]))
        except ZeroDivisionError:
            return None
        for r, j in enumerate(free):
            u[j] += step[r]
        lam = [lam[q] + step[nF + q] for q in range(nA)]
    else:
        return None
    # every KKT condition at the refined point
    if any(x < 0 for x in lam):
        return None
    cs = [cons(u, i) for i in range(k)]
    if any(c[0] < -mp.mpf(10) ** (-digits + 10) for c in cs):
        return None
    if any(not (lo[j] <= u[j] <= hi[j]) for j in range(m)):
        return None
    for j in range(m):
        if j in free:
            continue
        w = u[j] - un[j] - mp.fsum(lam[q] * cs[act[q]][1][j] for q in range(nA))
        if (at_lo[j] and w < 0) or (at_hi[j] and w > 0):
            return None
    return np.array([float(x) for x in u])


def fast_path_agreement(instances, low=None, high=None) -> dict:
    """The fast path against a high-precision reference on the instances: clarabel's answer
    (tol 1e-10) refined in 40-digit arithmetic (:func:`refine_kkt_mp`). Returns the share the
    fast path certifies, the largest ``|u_fast - u_ref|`` over those, how many exceed 1e-6,
    the same for clarabel's own answers, and how many references could not be refined
    (then clarabel's answer is the reference and ``fast_vs_clarabel_when_unrefined`` the
    largest difference); ``max_diff_vs_clarabel`` compares with clarabel's answers directly.
    ``working_set_*``: the same for the answers clarabel gave on a working set of the cones
    (feasible, not certified, fewer cones than the program)."""
    m = len(instances[0][0])
    low = -np.ones(m) if low is None else np.asarray(low, dtype=np.float64)
    high = np.ones(m) if high is None else np.asarray(high, dtype=np.float64)
    fast = SOCPFilter(low, high)
    ref = SOCPFilter(low, high, fast_path=False, tol=1e-10)
    n_active = n_cert = n_far = n_unrefined = n_clar_far = n_ws = n_ws_far = 0
    max_diff = max_clar = max_unrefined = max_vs_clarabel = max_ws = 0.0
    sizes: list[int] = []
    solve = fast.programs.solve

    def sized(kind, u_nom, a0, a, G=None):
        sizes.append(a0.size)
        return solve(kind, u_nom, a0, a, G)

    fast.programs.solve = sized
    for u, a0, a, G in instances:
        sizes.clear()
        r = fast.solve(u, a0, a, G)
        if r.status == "inactive":
            continue
        n_active += 1
        if not r.status.startswith("certified"):
            if r.feasible and sizes and sizes[-1] < len(a0):
                n_ws += 1
                rr = ref.solve(u, a0, a, G)
                exact = refine_kkt_mp(rr.u, u, a0, a, G, low, high) if rr.feasible else None
                if exact is not None:
                    d = float(np.abs(r.u - exact).max())
                    max_ws = max(max_ws, d)
                    n_ws_far += d > 1e-6
            continue
        n_cert += 1
        rr = ref.solve(u, a0, a, G)
        if not rr.feasible:
            n_far += 1  # certified but clarabel says infeasible: count as a disagreement
            continue
        max_vs_clarabel = max(max_vs_clarabel, float(np.abs(r.u - rr.u).max()))
        exact = refine_kkt_mp(rr.u, u, a0, a, G, low, high)
        if exact is None:
            n_unrefined += 1
            max_unrefined = max(max_unrefined, float(np.abs(r.u - rr.u).max()))
            continue
        d = float(np.abs(r.u - exact).max())
        max_diff = max(max_diff, d)
        n_far += d > 1e-6
        dc = float(np.abs(rr.u - exact).max())
        max_clar = max(max_clar, dc)
        n_clar_far += dc > 1e-6
    return {"instances": float(len(instances)), "active": float(n_active),
            "certified": float(n_cert),
            "certified_share": n_cert / n_active if n_active else 0.0,
            "max_diff_vs_reference": max_diff, "differ_over_1e-6": float(n_far),
            "max_diff_vs_clarabel": max_vs_clarabel,
            "clarabel_max_diff_vs_reference": max_clar,
            "clarabel_differ_over_1e-6": float(n_clar_far),
            "unrefined": float(n_unrefined),
            "fast_vs_clarabel_when_unrefined": max_unrefined,
            "working_set_answers": float(n_ws), "working_set_max_diff_vs_reference": max_ws,
            "working_set_differ_over_1e-6": float(n_ws_far)}


def solver_before_after(instances, before_path: str, low=None, high=None) -> dict[str, float]:
    """Per-call times of another ``SOCPFilter`` (the module file at ``before_path``, e.g. an
    older ``afvsgp_gym/cbf/socp.py``; constructed as ``SOCPFilter(low, high, k)``) and ours on
    the same instances, interleaved: median and p99 of each, over all calls and over the
    active ones (where ours is not ``"inactive"``), and the largest action difference."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("socp_before", before_path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclass looks its module up
    spec.loader.exec_module(mod)
    m = len(instances[0][0])
    low = -np.ones(m) if low is None else low
    high = np.ones(m) if high is None else high
    k = len(instances[0][1])
    old, new = mod.SOCPFilter(low, high, k), SOCPFilter(low, high)
    t_old, t_new, active, diff = [], [], [], 0.0
    for u, a0, a, G in instances:
        t0 = time.perf_counter()
        r_old = old.solve(u, a0, a, G)
        t1 = time.perf_counter()
        r_new = new.solve(u, a0, a, G)
        t2 = time.perf_counter()
        t_old.append(t1 - t0)
        t_new.append(t2 - t1)
        active.append(r_new.status != "inactive")
        if r_old.feasible and r_new.feasible:
            diff = max(diff, float(np.abs(r_old.u - r_new.u).max()))
    t_old, t_new, active = np.array(t_old[1:]), np.array(t_new[1:]), np.array(active[1:])
    out = {"calls": float(len(t_old)), "active_fraction": float(active.mean()),
           "max_action_diff": diff}
    for name, t in (("before", t_old), ("after", t_new)):
        for key, val in _stats(t).items():
            out[f"{name}_{key}"] = val
        if active.any():
            for key, val in _stats(t[active]).items():
                out[f"{name}_active_{key}"] = val
    return out


def main(argv=None) -> None:
    from afvsgp_gym.benchmarks._machine import machine

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--record", type=int, default=0, metavar="N",
                        help="record N Franka filter instances (half static, half dynamic) "
                             "and check the fast path against a 40-digit reference on them")
    parser.add_argument("--instances", default=None,
                        help=".npz to save the recorded instances to (or load them from)")
    parser.add_argument("--before", default=None, metavar="SOCP_PY",
                        help="time this socp.py against ours on every filter call of a "
                             "Franka episode (static, afvsgp, seed 0, all calls recorded)")
    args = parser.parse_args(argv)
    if not (args.record or args.before):
        parser.error("give --record N or --before SOCP_PY")
    print(f"machine: {machine()}", flush=True)
    if args.before:
        calls = record_filter_instances("afvsgp_gym/FrankaObstacleStatic-v0", 3000,
                                        seeds=range(1), active_only=False)
        for key, val in solver_before_after(calls, args.before).items():
            txt = f"{val * 1e6:10.1f} us" if key.endswith("_s") else f"{val:10.4g}"
            print(f"step_{key:<30} {txt}")
        return
    if args.instances and os.path.exists(args.instances):
        inst = load_instances(args.instances)
    else:
        half = args.record // 2
        inst = record_filter_instances("afvsgp_gym/FrankaObstacleStatic-v0", half)
        inst += record_filter_instances("afvsgp_gym/FrankaObstacleDynamic-v0",
                                        args.record - half)
        if args.instances:
            save_instances(args.instances, inst)
    for key, val in fast_path_agreement(inst).items():
        print(f"recorded_{key:<34} {val:.6g}")


if __name__ == "__main__":
    main()
