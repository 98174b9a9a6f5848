"""Filter-solve benchmark: our SOCPFilter against cbfpy and against clarabel's own solve time.

Problem ("sphere arm"): a kinematically linearised 7-joint arm, ``q'' = B u`` with
``B = diag(b)``, ``u`` in ``[-1, 1]^7``, K safety spheres with centres ``p_i(q) = c_i + J_i q``
and radii ``r_i``, one spherical obstacle ``(o, R)``: ``h_i = ||p_i - o|| - r_i - R``,
relative degree 2, HOCBF with linear gains ``alpha_1 = alpha_2 = 4`` (our default; cbfpy's
``alpha_2`` and ``alpha``). Known model: the QP of eq. 04. Learned: the same constraints with
a cone ``G_i = beta L_i'`` (eq. 05) of a synthetic posterior covariance. Every state is
``(q, q', o, u_des)``; both filters get the same states in the same run, interleaved.

Command line (``afvsgp-gym bench`` runs :func:`run`)::

    python -m afvsgp_gym.benchmarks.solver [--quick] [--no-cbfpy] [--barriers K ...]
                                           [--generic K ...]

Generic programs (:func:`generic_programs`, :func:`generic_vs_clarabel`): seeded random
feasible programs with random covariances (condition numbers up to 1e12), the proposal
outside the safe set, timed against a reused clarabel solver object of the same program.

cbfpy (``pip install afvsgp-gym[bench]``) is optional; without it that part is skipped. The
fast path against a 40-digit reference on recorded filter programs, and another ``socp.py``
timed against this one: ``benchmarks/solver_instances.py`` in the repository.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import numpy as np

from afvsgp_gym.cbf import SOCPFilter
from afvsgp_gym.cbf.cone_programs import ConePrograms

M = 7
ALPHA = (4.0, 4.0)


# ---------------------------------------------------------------------- problem
@dataclass(frozen=True)
class SphereArm:
    """Linearised arm with S spheres (``p_i = c[i] + J[i] q``, radii ``r``, gains ``b``) and
    ``n_obstacles`` spherical obstacles of radius ``R``: K = S * n_obstacles barriers."""

    c: np.ndarray  # (S, 3)
    J: np.ndarray  # (S, 3, 7)
    r: np.ndarray  # (S,)
    b: np.ndarray  # (7,)
    n_obstacles: int = 1
    R: float = 0.08

    @classmethod
    def make(cls, n_barriers: int, seed: int = 0) -> SphereArm:
        """K = 1: one sphere, one obstacle; K <= 21: K spheres, one obstacle; larger K:
        20 spheres and K / 20 obstacles. Seven joints along a 0.9 m chain with random unit
        axes ``w_j``; spheres spread along the chain, the first at its tip (the end-effector);
        ``J_i[:, j] = w_j x (c_i - x_j)`` for the joints ``x_j`` before sphere i (the
        geometric Jacobian of a serial arm), so neighbouring spheres move alike."""
        n_obs = 1 if n_barriers <= 21 else max(1, n_barriers // 20)
        n_spheres = n_barriers // n_obs
        if n_spheres * n_obs != n_barriers:
            raise ValueError(f"n_barriers must be <= 21 or a multiple of 20. Got: {n_barriers}")
        rng = np.random.default_rng(seed)
        chain = lambda s: np.stack([0.3 * s, 0.1 * np.sin(4 * s), 0.3 + 0.6 * s], axis=-1)  # noqa: E731
        s = np.linspace(1.0, 0.1, n_spheres)
        c = chain(s)
        x = chain(np.arange(M) / M)  # joint positions
        w = rng.normal(size=(M, 3))
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        J = np.cross(w[None], c[:, None] - x[None]).transpose(0, 2, 1)  # (S, 3, 7)
        J *= (np.arange(M) / M)[None, None, :] < s[:, None, None]
        r = rng.uniform(0.04, 0.08, n_spheres)
        return cls(c, J, r, np.full(M, 10.0), n_obs)

    def sample_states(self, n: int, seed: int = 1):
        """``n`` states: q, q' (n, 7), obstacle centres o (n, n_obstacles, 3), u_des (n, 7).
        Each obstacle is placed 0-10 cm outside a random sphere, on a random side; the arm
        moves at up to ~0.5 m/s; u_des is uniform in the box."""
        rng = np.random.default_rng(seed)
        S, n_obs = len(self.r), self.n_obstacles
        q = rng.uniform(-0.3, 0.3, (n, M))
        qd = rng.normal(scale=0.3, size=(n, M))
        i = rng.integers(0, S, (n, n_obs))
        p = self.c[i] + np.einsum("noij,nj->noi", self.J[i], q)
        d = rng.normal(size=(n, n_obs, 3))
        d /= np.linalg.norm(d, axis=2, keepdims=True)
        o = p + d * (self.r[i] + self.R + rng.uniform(0.02, 0.15, (n, n_obs)))[..., None]
        u_des = rng.uniform(-1.0, 1.0, (n, M))
        return q, qd, o, u_des

    def constraints(self, q, qd, o):
        """``(a0, a)`` of ``psi_2 = h'' + (a1 + a2) h' + a1 a2 h >= 0`` for every (obstacle,
        sphere) pair, obstacle-major."""
        a1, a2 = ALPHA
        p = self.c + self.J @ q  # (S, 3)
        v = self.J @ qd
        dvec = p[None] - o[:, None]  # (n_obs, S, 3)
        dist = np.linalg.norm(dvec, axis=2)
        n = dvec / dist[..., None]
        h = dist - self.r - self.R
        hd = np.einsum("osj,sj->os", n, v)
        curv = (np.einsum("sj,sj->s", v, v) - hd**2) / dist
        a0 = curv + (a1 + a2) * hd + a1 * a2 * h
        a = np.einsum("osj,sjk->osk", n, self.J) * self.b
        return a0.ravel(), a.reshape(-1, M)


def synthetic_cones(a: np.ndarray, rng, beta: float = 3.0) -> np.ndarray:
    """``G_i = beta L_i'`` (upper Cholesky factor) of a posterior covariance of ``Delta B``
    whose standard deviation is ~2 % of the constraint's action gain (as after warm-up)."""
    k = a.shape[0]
    out = np.zeros((k, M + 1, M + 1))
    for i in range(k):
        s = 0.02 * (1.0 + np.linalg.norm(a[i]))
        W = rng.normal(scale=s / np.sqrt(M + 1), size=(M + 1, M + 1))
        sig = W @ W.T + (0.1 * s) ** 2 * np.eye(M + 1)
        out[i] = beta * np.linalg.cholesky(sig).T
    return out


def make_instances(n_barriers: int, n: int, learned: bool, seed: int = 0):
    """``(arm, states, instances)``: ``instances`` a list of ``(u_nom, a0, a, G)`` on the
    sphere arm (G None when not ``learned``), ``states`` ``(q, q', o, u_des)`` for cbfpy."""
    arm = SphereArm.make(n_barriers, seed)
    q, qd, o, u_des = arm.sample_states(n, seed + 1)
    rng = np.random.default_rng(seed + 2)
    out = []
    for j in range(n):
        a0, a = arm.constraints(q[j], qd[j], o[j])
        G = synthetic_cones(a, rng) if learned else None
        out.append((u_des[j], a0, a, G))
    return arm, (q, qd, o, u_des), out


# ---------------------------------------------------------------------- timing helpers
def _stats(t: np.ndarray) -> dict[str, float]:
    return {"median_s": float(np.median(t)), "p99_s": float(np.percentile(t, 99))}


def filter_vs_clarabel(n_barriers: int, n: int, learned: bool, seed: int = 0) -> dict:
    """Our filter (fast paths on), our filter with clarabel for every active call, and
    clarabel's own ``solve()`` (a reused solver whose data were updated beforehand) on the
    same instances, interleaved. Medians and p99 over all calls, over the active ones and
    over the active feasible ones (the first call apart); ``overhead_*`` = median over the
    active feasible calls / clarabel's own median on them."""
    _, _, inst = make_instances(n_barriers, n, learned, seed)
    low, high = -np.ones(M), np.ones(M)
    fast, clar = SOCPFilter(low, high), SOCPFilter(low, high, fast_path=False)
    own = ConePrograms(low, high, 1e-9, 1e-4)
    kind = "qp" if not learned else "socp"
    t = np.full((3, n), np.nan)
    status = []
    for j, (u, a0, a, G) in enumerate(inst):
        t0 = time.perf_counter()
        res = fast.solve(u, a0, a, G)
        t1 = time.perf_counter()
        ref = clar.solve(u, a0, a, G)
        t[:2, j] = t1 - t0, time.perf_counter() - t1
        status.append((res.status, ref.feasible))
        if res.status != "inactive":
            own.solve(kind, u, a0, a, G)  # build or update, then time a solve on these data
            solver = own._solvers[(kind, a0.size)]
            t0 = time.perf_counter()
            solver.solve()
            t[2, j] = time.perf_counter() - t0
    t = t[:, 1:]
    active = np.array([st != "inactive" for st, _ in status])[1:]
    feas = active & np.array([ok for _, ok in status])[1:]
    certified = np.array([st.startswith("certified") for st, _ in status])[1:]
    out = {"active_fraction": float(active.mean()),
           "feasible_fraction_of_active": float(feas.sum() / max(active.sum(), 1)),
           "certified_share_of_active": float(certified.sum() / max(active.sum(), 1))}
    for i, name in enumerate(("filter", "filter_clarabel_only")):
        for sel, tag in ((np.ones_like(active), ""), (active, "active_"), (feas, "feasible_")):
            if sel.any():
                for key, val in _stats(t[i][sel]).items():
                    out[f"{name}_{tag}{key}"] = val
    if feas.any():
        for key, val in _stats(t[2][feas]).items():
            out[f"clarabel_own_feasible_{key}"] = val
        own_med = float(np.median(t[2][feas]))
        out["overhead_clarabel_path"] = float(np.median(t[1][feas])) / own_med
        out["overhead_filter"] = float(np.median(t[0][feas])) / own_med
    return out


# ---------------------------------------------------------------------- generic programs
#: ``beta`` of the generic programs' cones (the filter's default chance-constraint factor).
GENERIC_BETA = 2.5


def generic_programs(n: int, n_cones: int, seed: int = 0, max_condition: float = 1e12):
    """``n`` seeded random feasible programs ``(u_nom, a0, a, G)`` with ``n_cones`` cones on
    M = 7 actions in ``[-1, 1]^7`` (the Franka's), each active: its clipped proposal violates
    a cone.

    Cone i: ``a_i`` standard normal and ``G_i = beta L_i'`` (the upper Cholesky factor, as
    the filter's) of a random covariance ``Sigma_i = Q diag(s^2 r_j) Q'`` (Q a random
    rotation), its largest standard deviation ``s`` log-uniform in ``[0.01, 0.3] ||a_i||``
    and its condition number log-uniform in ``[1, max_condition]`` (``r_j`` geometric from 1
    to its inverse). ``a0_i`` gives a random point of the inner 60 % of the box the margin
    ``[0.02, 0.3] ||a_i||`` on every cone (so the program is feasible); ``u_nom`` is uniform
    in 1.5 times the box (a third of its coordinates outside it), drawn again until the
    clipped proposal violates a cone."""
    rng = np.random.default_rng(seed)
    n1 = M + 1
    out = []
    while len(out) < n:
        a = rng.normal(size=(n_cones, M))
        G = np.empty((n_cones, n1, n1))
        for i in range(n_cones):
            Q = np.linalg.qr(rng.normal(size=(n1, n1)))[0]
            s = np.linalg.norm(a[i]) * 10.0 ** rng.uniform(-2.0, math.log10(0.3))
            ev = s * s * np.logspace(0.0, -rng.uniform(0.0, math.log10(max_condition)), n1)
            sigma = (Q * ev) @ Q.T
            G[i] = GENERIC_BETA * np.linalg.cholesky(0.5 * (sigma + sigma.T)).T
        u_star = rng.uniform(-0.6, 0.6, M)
        a0 = (np.linalg.norm(G @ np.concatenate([[1.0], u_star]), axis=1) - a @ u_star
              + np.linalg.norm(a, axis=1) * rng.uniform(0.02, 0.3, n_cones))
        while True:
            u_nom = rng.uniform(-1.5, 1.5, M)
            ubar = np.concatenate([[1.0], np.clip(u_nom, -1.0, 1.0)])
            if float((a0 + a @ ubar[1:] - np.linalg.norm(G @ ubar, axis=1)).min()) < 0.0:
                break
        out.append((u_nom, a0, a, G))
    return out


def generic_vs_clarabel(n_cones: int, n: int, seed: int = 0, repeats: int = 5) -> dict:
    """Our filter (default backend, and the numpy paths only) against a reused raw clarabel
    solve of the same programs (:func:`generic_programs`), interleaved in one run.

    Clarabel: one ``DefaultSolver`` built once, with the filter's settings and data layout
    (:mod:`afvsgp_gym.cbf.cone_programs`); per program its ``update(q, b, A)`` and
    ``solve()`` are timed, the data being arranged beforehand (untimed). After one untimed
    pass, ``repeats`` passes over the programs, each program solved by the three in turn
    (the order rotating); per program the median over the passes. ``ratio_*``: median and
    p90 over programs of (filter / clarabel), ``ratio_numpy_*`` the same for the numpy
    paths; ``n_<status>``: programs per status of the filter (default backend) and
    ``ratio_median_<status>`` over them; ``max_action_diff``: the largest ``|u_filter -
    u_clarabel|`` (clarabel at tolerance 1e-9) over the programs it solved."""
    from afvsgp_gym.cbf.cone_programs import SOLVED

    inst = generic_programs(n, n_cones, seed)
    low, high = -np.ones(M), np.ones(M)
    ours, numpy_only = SOCPFilter(low, high), SOCPFilter(low, high, backend="numpy")
    raw = ConePrograms(low, high, ours.tol, ours.fallback_regularization)
    raw.prepare("socp", [n_cones])
    solver = raw._solvers[("socp", n_cones)]
    data = []
    for u_nom, a0, a, G in inst:
        values, b = raw._fill("socp", a0, a, G)
        data.append((-u_nom, b.copy(), values.copy()))
    t = np.full((repeats, 3, n), np.nan)
    t_solve = np.full((repeats, n), np.nan)
    status: list[str] = []
    ours_u, raw_u = np.empty((n, M)), np.full((n, M), np.nan)
    for rep in range(-1, repeats):
        for j, (u_nom, a0, a, G) in enumerate(inst):
            for turn in range(3):
                which = (turn + j + rep) % 3
                t0 = time.perf_counter()
                if which == 0:
                    res = ours.solve(u_nom, a0, a, G)
                elif which == 1:
                    numpy_only.solve(u_nom, a0, a, G)
                else:
                    q, b, values = data[j]
                    solver.update(q=q, b=b, A=values)
                    t1 = time.perf_counter()
                    sol = solver.solve()
                    t_end = time.perf_counter()
                    if rep >= 0:
                        t[rep, 2, j], t_solve[rep, j] = t_end - t0, t_end - t1
                    if rep < 0 and str(sol.status) in SOLVED:
                        raw_u[j] = np.asarray(sol.x)[:M]
                    continue
                t_end = time.perf_counter()
                if rep >= 0:
                    t[rep, which, j] = t_end - t0
                elif which == 0:
                    status.append(res.status)
                    ours_u[j] = res.u
    med = np.median(t, axis=0)
    ratio, ratio_np = med[0] / med[2], med[1] / med[2]
    out: dict[str, float] = {}
    for name, i in (("filter", 0), ("filter_numpy", 1), ("clarabel", 2)):
        out[f"{name}_median_s"] = float(np.median(med[i]))
        out[f"{name}_p90_s"] = float(np.percentile(med[i], 90))
    out["clarabel_solve_only_median_s"] = float(np.median(np.median(t_solve, axis=0)))
    for tag, r in (("", ratio), ("numpy_", ratio_np)):
        out[f"ratio_{tag}median"] = float(np.median(r))
        out[f"ratio_{tag}p90"] = float(np.percentile(r, 90))
    status = np.array(status)
    for st in sorted(set(status.tolist())):
        sel = status == st
        out[f"n_{st}"] = int(sel.sum())
        out[f"ratio_median_{st}"] = float(np.median(ratio[sel]))
    solved = ~np.isnan(raw_u[:, 0])
    out["max_action_diff"] = float(np.abs(ours_u - raw_u)[solved].max(initial=0.0))
    return out


# ---------------------------------------------------------------------- cbfpy
def cbfpy_filters(arm: SphereArm):
    """``{name: jitted safety_filter(z, u_des, o)}`` for cbfpy's configurations on the arm
    (qpax soft, qpax hard, elastiqp soft where installed). Raises ImportError without cbfpy."""
    import os

    # cbfpy's recommended CPU settings (effective if jax is not imported yet)
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    os.environ.setdefault("JAX_ENABLE_X64", "1")
    import jax
    import jax.numpy as jnp
    from cbfpy import CBF, CBFConfig

    jax.config.update("jax_enable_x64", True)
    c, J, r, b = (jnp.asarray(x) for x in (arm.c, arm.J, arm.r, arm.b))
    R, n_obs = arm.R, arm.n_obstacles
    a1, a2 = ALPHA

    class ArmConfig(CBFConfig):
        def __init__(self, **kw):
            super().__init__(n=2 * M, m=M, u_min=-np.ones(M), u_max=np.ones(M),
                             init_args=(np.zeros((n_obs, 3)),), **kw)

        def f(self, z, o):
            return jnp.concatenate([z[M:], jnp.zeros(M)])

        def g(self, z, o):
            return jnp.concatenate([jnp.zeros((M, M)), jnp.diag(b)])

        def h_2(self, z, o):  # obstacle-major, as SphereArm.constraints
            p = c + J @ z[:M]
            return (jnp.linalg.norm(p[None] - o[:, None], axis=2) - r - R).ravel()

        def alpha(self, h, o):
            return a2 * h

        def alpha_2(self, h2, o):
            return a1 * h2

    configs = {
        "cbfpy_qpax_soft": dict(relax_qp=True),
        "cbfpy_qpax_hard": dict(relax_qp=False),
    }
    try:
        import elastiqp.jax  # noqa: F401

        configs["cbfpy_elastiqp_soft"] = dict(relax_qp=True, backend="elastiqp", solver_tol=1e-6)
    except ImportError:
        pass
    return {name: CBF.from_config(ArmConfig(**kw)).safety_filter for name, kw in configs.items()}


def cbfpy_comparison(n_barriers: int, n: int, seed: int = 0, block: int = 50) -> dict:
    """cbfpy's configurations and our known-model filter on the same states in one run:
    blocks of ``block`` states, each solved by ours and then by every cbfpy configuration
    (``block=1`` interleaves every call; the code of one filter then evicts the other's from
    the caches, which costs ours about as much as its solve; docs/performance.md has the
    figures of ``block=50``).
    ``ours_with_backup``: ours given a backup action (a joint-damping brake, as the env
    wrapper passes one), returned flagged on infeasible states instead of the
    max-worst-margin fallback. Median / p99 per call (first call of each apart,
    ``first_call_s``) over all states, the active ones (our clipped proposal unsafe) and the
    active feasible ones; the largest difference of the actions and each one's worst
    constraint violation (box excess, or ``-c_i / scale_i`` with
    :func:`~afvsgp_gym.cbf.fastpath.constraint_scales`) over the states where our program is
    feasible."""
    import jax.numpy as jnp

    from afvsgp_gym.cbf.fastpath import constraint_scales

    arm, (q, qd, o, u_des), inst = make_instances(n_barriers, n, learned=False, seed=seed)
    fns = cbfpy_filters(arm)
    f = SOCPFilter(-np.ones(M), np.ones(M))
    brake = np.clip(-qd, -1.0, 1.0)  # a joint-damping brake as the backup action
    names = ["ours", "ours_with_backup", *fns]
    times = {k: np.empty(n) for k in names}
    actions = {k: np.empty((n, M)) for k in names}
    active, feasible = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    z = [jnp.asarray(np.concatenate([q[j], qd[j]])) for j in range(n)]
    ud = [jnp.asarray(u_des[j]) for j in range(n)]
    oj = [jnp.asarray(o[j]) for j in range(n)]
    for start in range(0, n, block):
        idx = range(start, min(start + block, n))
        for j in idx:
            u0, a0, a, _ = inst[j]
            t0 = time.perf_counter()
            res = f.solve(u0, a0, a)
            times["ours"][j] = time.perf_counter() - t0
            actions["ours"][j] = res.u
            active[j], feasible[j] = res.status != "inactive", res.feasible
        for j in idx:
            u0, a0, a, _ = inst[j]
            t0 = time.perf_counter()
            res = f.solve(u0, a0, a, backup=brake[j])
            times["ours_with_backup"][j] = time.perf_counter() - t0
            actions["ours_with_backup"][j] = res.u
        for name, fn in fns.items():
            for j in idx:
                t0 = time.perf_counter()
                u = fn(z[j], ud[j], oj[j]).block_until_ready()
                times[name][j] = time.perf_counter() - t0
                actions[name][j] = np.asarray(u, dtype=np.float64)
    worst = {k: 0.0 for k in names}
    diff = {k: 0.0 for k in fns}
    for j in np.flatnonzero(feasible):
        u0, a0, a, _ = inst[j]
        scales = constraint_scales(a0, a, None, f.bound_norm)
        for name in names:
            u = actions[name][j]
            excess = float(np.maximum(np.abs(u) - 1.0, 0.0).max())
            worst[name] = max(worst[name], excess, float(-np.min((a0 + a @ u) / scales)))
            if name in diff:
                diff[name] = max(diff[name], float(np.abs(u - actions["ours"][j]).max()))
    out = {"active_fraction": float(active[1:].mean()),
           "feasible_fraction": float(feasible[1:].mean())}
    act, act_feas = active[1:], (active & feasible)[1:]
    for name in names:
        out[f"{name}_first_call_s"] = float(times[name][0])
        t = times[name][1:]
        for sel, tag in ((np.ones_like(act), ""), (act, "active_"), (act_feas, "feasible_")):
            if sel.any():
                for key, val in _stats(t[sel]).items():
                    out[f"{name}_{tag}{key}"] = val
        out[f"{name}_worst_violation"] = float(worst[name])
    for name in fns:
        out[f"{name}_max_action_diff"] = diff[name]
    return out


# ---------------------------------------------------------------------- entry points
def _have_cbfpy() -> bool:
    try:
        import cbfpy  # noqa: F401
    except ImportError:
        return False
    return True


def run(quick: bool = False, cbfpy: bool | None = None, cbfpy_only: bool = False,
        block: int = 50, barriers=(1, 21, 100), generic=(1, 3)) -> dict[str, float]:
    """Filter vs clarabel at 1 / 21 / 100 barriers (or those in ``barriers``), known model and
    learned; with ``cbfpy`` (default: when it is installed) also cbfpy's configurations on the
    known-model states (``cbfpy_only``: only those); then on generic programs with 1 and 3
    cones (or those in ``generic``, :func:`generic_vs_clarabel`, keys ``generic_K<k>_*``)."""
    cbfpy = _have_cbfpy() if cbfpy is None else cbfpy
    n = 200 if quick else 2000
    out: dict[str, float] = {}
    for K in barriers:
        if cbfpy:
            for key, val in cbfpy_comparison(K, n, block=block).items():
                out[f"K{K}_qp_{key}"] = val
        if cbfpy_only:
            continue
        for learned in (False, True):
            tag = f"K{K}_{'socp' if learned else 'qp'}"
            for key, val in filter_vs_clarabel(K, n, learned).items():
                out[f"{tag}_{key}"] = val
    if not cbfpy_only:
        for k in generic:
            for key, val in generic_vs_clarabel(k, n // 2).items():
                out[f"generic_K{k}_{key}"] = val
    return out


def main(argv=None) -> None:
    from afvsgp_gym.benchmarks._machine import machine

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="200 states instead of 2000")
    parser.add_argument("--no-cbfpy", action="store_true", help="skip cbfpy even if installed")
    parser.add_argument("--cbfpy-only", action="store_true",
                        help="only cbfpy against our known-model filter")
    parser.add_argument("--barriers", type=int, nargs="*", default=[1, 21, 100],
                        metavar="K", help="numbers of barriers to run (default: 1 21 100)")
    parser.add_argument("--generic", type=int, nargs="*", default=[1, 3], metavar="K",
                        help="numbers of cones of the generic programs (default: 1 3)")
    parser.add_argument("--block", type=int, default=50,
                        help="states per block of the cbfpy comparison (1: every call "
                             "interleaved)")
    args = parser.parse_args(argv)
    print(f"machine: {machine()}", flush=True)
    res = run(quick=args.quick, cbfpy=False if args.no_cbfpy else None,
              cbfpy_only=args.cbfpy_only, block=args.block, barriers=args.barriers,
              generic=args.generic)
    width = max(len(k) for k in res)
    for key, val in res.items():
        txt = f"{val * 1e6:10.1f} us" if key.endswith("_s") else f"{val:10.4g}"
        print(f"{key:<{width}}  {txt}")


if __name__ == "__main__":
    main()
