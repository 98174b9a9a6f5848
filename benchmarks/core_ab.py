"""The learners' compiled core against another build of it, in one process.

    python benchmarks/core_ab.py OTHER_BANK_SO [--episode-seeds 0 1] [--calls 4000]

``OTHER_BANK_SO`` is another build's ``afvsgp_gym/gp/_bank*.so`` (e.g. a worktree of an
earlier commit, built in place). On the bank of the 21-barrier static episode after 300 timed
steps, the installed core (``new``) and the other (``old``) are called in turn, the order
alternating, on the same state: ``update`` (all 21 learners) in a tight loop and after writing
8 MB (the caches emptied, as between control steps), ``predict`` of 5 learners with their
factor rebuilt, and ``candidate`` (one learner's window scan); their outputs are compared bit
for bit first. Then two 21-barrier episodes per seed advance in lockstep, one on each core
(one control step each in turn), and their step, learners' and update medians / p99 are
printed. Ratios are new / old, measured on the same seconds; pin to one core (``taskset -c 0``)
with ``OPENBLAS_NUM_THREADS=1``.
"""

from __future__ import annotations

import argparse
import importlib.util
import time

import numpy as np

import afvsgp_gym.gp.afvsgp_bank as bank_module
from afvsgp_gym.benchmarks.arm import CONFIGS, TimedEpisode

ARM = "21 (arm)"


def load_core(path: str):
    """The compiled core built at ``path``, as a module apart from the installed one."""
    spec = importlib.util.spec_from_file_location("other_core._bank", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"OTHER_BANK_SO: cannot load {path!r}")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def recorded_bank(steps: int = 300):
    """The AFVSGP bank of the 21-barrier static episode (seed 0) after ``steps`` timed steps."""
    ep = TimedEpisode(CONFIGS[ARM], steps=steps, seed=0)
    while ep.remaining > 0:
        ep.step()
    return ep.env.controller.bank.bank


def by_dimension(core) -> bool:
    """Whether ``core`` takes the inducing inputs by dimension, (K, b, Mp), as the bank stores
    them; a core built before they were (commit 0c0e367 and earlier) takes them by point, (K,
    Mp, b)."""
    return getattr(core, "INDUCING_INPUTS", None) == "by dimension"


def whitened(core) -> bool:
    """Whether ``core``'s update and predict keep the whitened statistics (their last
    arguments ``l_oo, lsl, white`` and ``lsl, white``); a core built before they did (commit
    befa8d3 and earlier) takes neither."""
    return getattr(core, "WHITENED_STATISTICS", 0) == 1


class Shim:
    """``core`` with its ``update`` and ``predict`` given ``by_point`` (a C-ordered (K, Mp, b)
    copy of the bank's inducing inputs, refreshed by the caller after each control step) in
    place of the bank's array, unless the core takes them by dimension, and without the
    whitened statistics' arguments, unless it keeps them. Both cores of a lockstep run go
    through one, so that the wrapper's cost is the same for both."""

    def __init__(self, core):
        self.core, self.by_point = core, None
        self.passthrough = by_dimension(core)
        self.whitened = whitened(core)

    def update(self, dims, ind, *rest):
        rest = rest if self.whitened else rest[:-3]
        return self.core.update(dims, ind if self.passthrough else self.by_point, *rest)

    def predict(self, dims, n, ind, *rest):
        rest = rest if self.whitened else rest[:-2]
        return self.core.predict(dims, n, ind if self.passthrough else self.by_point, *rest)

    def __getattr__(self, name):
        return getattr(self.core, name)


def calls(b) -> dict:
    """name -> function(core) running that core entry on bank ``b`` and returning its outputs."""
    t = 3  # a window slot: its inputs make a realistic sample
    xi = np.ascontiguousarray(b._wxt[:, :, t])
    ub = np.concatenate([[1.0], b._wubt[0, 1:, t]])
    z = np.zeros(b.n_learners)
    k_new, kss, resid = b._step_out
    by_point = np.ascontiguousarray(b._ind_xi)
    ind = {True: b._ind_xit, False: by_point}

    def update(core):
        core.update(b._dims, ind[by_dimension(core)], b.log_var, b.inv_ls2, b._ubt, b.var,
                    b._koo_inv, b._stats, b._scale, b._wk, b._wz, b._wxt, b._wubt, xi, ub, z,
                    k_new, kss, resid, b._work, b._head, b._count, b.n_seen_, b._fresh,
                    b._since_refresh, b.noise_variance, b._inv_phi, b._phi_p, b._add_floor,
                    10**12, *((b._l_oo, b._lsl, b._white) if whitened(core) else ()))
        return k_new.copy(), resid.copy()

    rows = np.array([3, 7, 12, 15, 20], dtype=np.int64)
    pxi = np.ascontiguousarray(b._wxt[rows, :, t + 2])
    bvec, sig = np.empty((len(rows), b._c)), np.empty((len(rows), b._c, b._c))

    def predict(core):
        b._fresh[:] = False  # the factor L_D rebuilt, as every step
        b._white[:] = False  # and the whitened statistics solved afresh: the older cores' work
        rc = core.predict(b._dims, len(rows), ind[by_dimension(core)], b.log_var, b.inv_ls2,
                          b._ubt, b.var, b._l_oo, b._stats, b._scale, b.noise_variance,
                          b._l_d, b._cvec, b._fresh, rows, pxi, bvec, sig, b._work,
                          *((b._lsl, b._white) if whitened(core) else ()))
        return rc, bvec.copy(), sig.copy()

    k = 5
    cxi = np.ascontiguousarray(b._wxt[k, :, 7] + 0.05)
    cub = np.concatenate([[1.0], b._wubt[k, 1:, 7]])

    def candidate(core):
        lvec, col, srow = np.empty(b._mp), np.empty(b.window), np.empty(b._mp)
        out = core.candidate(b._dims, k, int(b.n_inducing_[k]), int(b._head[k]),
                             int(b._count[k]), 1.0, float(b.jitter[k]), -1e300, b._l_oo,
                             b._koo_inv, b._stats, b._scale, b._wk, b._wz, b._wxt, b._wubt,
                             b.inv_ls2, b.log_var, b._pow_rev, cxi, cub,
                             np.ascontiguousarray(0.1 * k_new[k]), lvec, col, srow, b._work)
        return out, lvec, col, srow

    return {"update": update, "predict": predict, "candidate": candidate}


def same(x, y) -> bool:
    if isinstance(x, tuple):
        return all(same(a, c) for a, c in zip(x, y, strict=True))
    return bool(np.array_equal(x, y)) if isinstance(x, np.ndarray) else x == y


def interleaved(fn, cores: dict, n: int, thrash: bool = False) -> dict[str, float]:
    """Median seconds of ``fn(core)`` per core, called in turn (order alternating)."""
    big = np.zeros(2**20)  # 8 MB
    times: dict[str, list] = {name: [] for name in cores}
    names = list(cores)
    for i in range(n):
        for name in names if i % 2 else names[::-1]:
            if thrash:
                big += 1.0
            t0 = time.perf_counter()
            fn(cores[name])
            times[name].append(time.perf_counter() - t0)
    return {name: float(np.median(v)) for name, v in times.items()}


def lockstep(cores: dict, seed: int, steps: int = 1500) -> dict[str, dict[str, float]]:
    """Two 21-barrier episodes of ``seed`` advanced one step each in turn, one per core."""
    eps = {name: TimedEpisode(CONFIGS[ARM], steps=steps, seed=seed) for name in cores}
    shims = {name: Shim(core) for name, core in cores.items()}
    installed, order = bank_module._core, list(cores)
    try:
        while any(ep.remaining > 0 for ep in eps.values()):
            for name in order:
                bank_module._core = shims[name]
                eps[name].step()
                bank = getattr(eps[name].env.controller.bank, "bank", None)
                if bank is not None and not shims[name].passthrough:  # between steps
                    shims[name].by_point = np.ascontiguousarray(bank._ind_xi)
            order.reverse()
    finally:
        bank_module._core = installed
    out = {}
    for name, ep in eps.items():
        r = ep.result()
        out[name] = {f"{k} {q}": float(np.percentile(r[k], p)) for k in ("step", "learners",
                     "update") for q, p in (("median", 50), ("p99", 99))}
    return out


def main(argv: list[str] | None = None) -> None:
    from afvsgp_gym.benchmarks._machine import calibration_line, machine

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("other", metavar="OTHER_BANK_SO", help="another build's _bank*.so")
    p.add_argument("--calls", type=int, default=4000, help="calls per core and entry")
    p.add_argument("--episode-seeds", type=int, nargs="*", default=[0, 1])
    args = p.parse_args(argv)
    new = bank_module._core
    if new is None:
        raise SystemExit("the installed package has no compiled core (afvsgp_gym.gp._bank)")
    cores = {"old": load_core(args.other), "new": new}
    print(machine())
    print(calibration_line(), flush=True)
    b = recorded_bank()
    for name, fn in calls(b).items():
        print(f"{name}: outputs bit-identical: {same(fn(cores['old']), fn(cores['new']))}")
        for thrash in (False, True) if name == "update" else (False,):
            med = interleaved(fn, cores, args.calls, thrash)
            label = f"{name}{' after 8 MB written' if thrash else ''}"
            print(f"{label:32s} old {med['old'] * 1e6:7.1f} us  new {med['new'] * 1e6:7.1f} us"
                  f"  new/old {med['new'] / med['old']:.3f}", flush=True)
    for seed in args.episode_seeds:
        res = lockstep(cores, seed)
        for key in res["old"]:
            o, n = res["old"][key], res["new"][key]
            print(f"episode seed {seed}, {key:16s} old {o * 1e6:7.0f} us  new {n * 1e6:7.0f} us"
                  f"  new/old {n / o:.3f}", flush=True)


if __name__ == "__main__":
    main()
