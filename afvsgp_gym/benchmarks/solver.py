"""Filter-solve benchmark: our SOCPFilter against cbfpy and against clarabel's own solve time.

Problem ("sphere arm"): a kinematically linearised 7-joint arm, ``q'' = B u`` with
``B = diag(b)``, ``u`` in ``[-1, 1]^7``, K safety spheres with centres ``p_i(q) = c_i + J_i q``
and radii ``r_i``, one spherical obstacle ``(o, R)``: ``h_i = ||p_i - o|| - r_i - R``,
relative degree 2, HOCBF with linear gains ``alpha_1 = alpha_2 = 4`` (our default; cbfpy's
``alpha_2`` and ``alpha``). Known model: the QP of eq. 04. Learned: the same constraints with
a cone ``G_i = beta L_i'`` (eq. 05) of a synthetic posterior covariance. Every state is
``(q, q', o, u_des)``; both filters get the same states in the same run, interleaved.

``record_filter_instances`` records ``(u_nom, a0, a, G)`` of every cone program a
:class:`~afvsgp_gym.wrappers.SafetyFilter` solves on a registered env; ``fast_path_agreement``
compares the fast path with clarabel on recorded instances. Command line::

    python -m afvsgp_gym.benchmarks.solver [--quick] [--no-cbfpy]
    python -m afvsgp_gym.benchmarks.solver --record N [--instances file.npz]

cbfpy (``pip install afvsgp-gym[bench]``) is optional; without it that part is skipped.
"""

from __future__ import annotations

import argparse
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
    the caches, which costs ours about as much as its solve, see benchmarks/solver.md).
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


# ---------------------------------------------------------------------- recorded instances
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


# ---------------------------------------------------------------------- entry points
def _have_cbfpy() -> bool:
    try:
        import cbfpy  # noqa: F401
    except ImportError:
        return False
    return True


def run(quick: bool = False, cbfpy: bool | None = None, cbfpy_only: bool = False,
        block: int = 50, barriers=(1, 21, 100)) -> dict[str, float]:
    """Filter vs clarabel at 1 / 21 / 100 barriers (or those in ``barriers``), known model and
    learned; with ``cbfpy`` (default: when it is installed) also cbfpy's configurations on the
    known-model states (``cbfpy_only``: only those)."""
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
    return out


def main(argv=None) -> None:
    import os

    from afvsgp_gym.benchmarks._machine import machine

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="200 states instead of 2000")
    parser.add_argument("--no-cbfpy", action="store_true", help="skip cbfpy even if installed")
    parser.add_argument("--cbfpy-only", action="store_true",
                        help="only cbfpy against our known-model filter")
    parser.add_argument("--barriers", type=int, nargs="+", default=[1, 21, 100],
                        metavar="K", help="numbers of barriers to run (default: 1 21 100)")
    parser.add_argument("--block", type=int, default=50,
                        help="states per block of the cbfpy comparison (1: every call "
                             "interleaved)")
    parser.add_argument("--record", type=int, default=0, metavar="N",
                        help="record N Franka filter instances (half static, half dynamic) "
                             "and check the fast path against a 40-digit reference on them")
    parser.add_argument("--instances", default=None,
                        help=".npz to save the recorded instances to (or load them from)")
    parser.add_argument("--before", default=None, metavar="SOCP_PY",
                        help="time this socp.py against ours on every filter call of a "
                             "Franka episode (static, afvsgp, seed 0, all calls recorded)")
    args = parser.parse_args(argv)
    print(f"machine: {machine()}", flush=True)
    if args.before:
        calls = record_filter_instances("afvsgp_gym/FrankaObstacleStatic-v0", 3000,
                                        seeds=range(1), active_only=False)
        for key, val in solver_before_after(calls, args.before).items():
            txt = f"{val * 1e6:10.1f} us" if key.endswith("_s") else f"{val:10.4g}"
            print(f"step_{key:<30} {txt}")
        return
    if args.record:
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
        return
    res = run(quick=args.quick, cbfpy=False if args.no_cbfpy else None,
              cbfpy_only=args.cbfpy_only, block=args.block, barriers=args.barriers)
    width = max(len(k) for k in res)
    for key, val in res.items():
        txt = f"{val * 1e6:10.1f} us" if key.endswith("_s") else f"{val:10.4g}"
        print(f"{key:<{width}}  {txt}")


if __name__ == "__main__":
    main()
