"""The safety controller's compiled glue against its numpy version, in one process.

    python benchmarks/glue_ab.py [--seeds 0 1 2] [--steps 1500]

The glue is the elementwise arithmetic of the step between the learners, the solver and the
products by matrices: the barriers in the program, the learned terms added to the
constraints with the cone matrices, the eq. 48 samples, the residual observer
(``afvsgp_gym.cbf._step``), and the copies that install a new inducing point
(``afvsgp_gym.gp._bank.install``). Two 21-barrier episodes per seed (those of
``afvsgp_gym.benchmarks.arm``) advance in lockstep, one control step each in turn: one with
the compiled glue, one with the numpy versions (the controller's two compiled steps and the
bank's install overridden on their instances, the other modules' ``_step`` set to None;
the install then makes its copies in numpy and calls the core's ``factor_inverse``, as
before the compiled install). Their observations
are compared bit for bit (the same digits by construction); prints the step and filter
medians / p99 of both and their ratios, measured on the same seconds. Pin to one core
(``taskset -c 0``) with ``OPENBLAS_NUM_THREADS=1``.
"""

from __future__ import annotations

import argparse

import numpy as np

from afvsgp_gym.benchmarks._machine import calibration_line, machine
from afvsgp_gym.benchmarks.arm import CONFIGS, TimedEpisode
from afvsgp_gym.cbf import controller, measurement, residuals
from afvsgp_gym.gp import afvsgp_bank

ARM = "21 (arm)"
MODULES = (measurement, residuals)


def numpy_install(bank):
    """``bank._install`` with the copies in numpy and K_oo^-1 by the core's factor_inverse."""
    core = afvsgp_bank._core

    def install(k, xi, ub, kss, k_new, cand):
        m = int(bank.n_inducing_[k])
        pos, mm = (m, m + 1) if cand.drop is None else (cand.drop, m)
        bank._set_exponent_rows(k, pos, xi)
        bank._install_copies(k, m, pos, mm, xi, ub, kss + bank.jitter[k], k_new, cand)
        if core.factor_inverse(bank._dims, k, mm, cand.drop is not None, bank._koo,
                               bank._l_oo, bank._koo_inv, bank._fresh) != 0:
            raise RuntimeError("K_oo not positive definite: not timed here")
        bank.n_inducing_[k] = mm

    return install


def lockstep(seed: int, steps: int) -> tuple[dict[str, dict[str, np.ndarray]], bool]:
    """Per-step times of the two episodes of ``seed`` and whether their observations were
    equal at every step."""
    step = controller._step
    if step is None:
        raise SystemExit("the compiled glue (afvsgp_gym.cbf._step) is not built")
    eps = {name: TimedEpisode(CONFIGS[ARM], steps=steps, seed=seed)
           for name in ("compiled", "numpy")}
    ctrl = eps["numpy"].env.controller
    ctrl._finite_active_rows = lambda c0, c, bset: None
    ctrl._learned_terms = lambda a0, a, bvec, rows, sig: (False, None)
    glue = {"compiled": step, "numpy": None}
    same, order = True, list(eps)
    try:
        while any(ep.remaining > 0 for ep in eps.values()):
            for name in order:
                for mod in MODULES:
                    mod._step = glue[name]
                eps[name].step()
            bank = getattr(ctrl.bank, "bank", None)  # the numpy side's, after the warm-up
            if bank is not None and "_install" not in vars(bank):
                bank._install = numpy_install(bank)
            order.reverse()
            same &= bool(np.array_equal(eps["compiled"].obs, eps["numpy"].obs))
    finally:
        for mod in MODULES:
            mod._step = step
    return {name: ep.result() for name, ep in eps.items()}, same


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=1500, help="timed steps per episode")
    args = p.parse_args(argv)
    print(machine())
    print(calibration_line(), flush=True)
    times: dict[str, dict[str, list]] = {"compiled": {}, "numpy": {}}
    for seed in args.seeds:
        res, same = lockstep(seed, args.steps)
        print(f"seed {seed}: observations bit-identical at every step: {same}", flush=True)
        for name, r in res.items():
            for key in ("step", "filter"):
                times[name].setdefault(key, []).append(r[key])
    for key in ("step", "filter"):
        for q, pct in (("median", 50), ("p99", 99)):
            c, n = (float(np.percentile(np.concatenate(times[name][key]), pct)) * 1e6
                    for name in ("compiled", "numpy"))
            print(f"{key} {q:6s}  numpy {n:6.0f} us  compiled {c:6.0f} us  "
                  f"compiled/numpy {c / n:.3f}")


if __name__ == "__main__":
    main()
