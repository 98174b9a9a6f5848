"""The warm-up hyperparameter fit in the closed loop: filter sweeps with the conditioning of each
learner right after its warm-up fit (the design is in docs/learners.md).

Every episode is :func:`afvsgp_gym.benchmarks.filter.run_episode` with the given learner; right
after the warm-up fit it records, per barrier, ``cond(K_oo)`` and ``cond(K_oo + S/s2)`` (2-norm,
float64 SVD) and the learned noise variance. ``--prior`` overrides the learners' prior
(:class:`afvsgp_gym.gp.hyper.LogNormalPrior` standard deviations, ``none`` for no prior).
Command line::

    python benchmarks/gp_fit.py [--scenarios franka_static:0-49 ...]
        [--learner afvsgp] [--prior 1.5,1.5 | none] [--json PATH]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

__all__ = ["conditioning", "main", "run"]

DEFAULT_SCENARIOS = ("franka_static:0-9", "franka_dynamic:0-9", "franka_random:0-9")


def conditioning(controller) -> dict:
    """Conditioning and noise of the controller's sparse learners (max over barriers)."""
    bank = getattr(controller.bank, "bank", None)  # AFVSGP: the stacked learners
    if bank is not None:
        ck, cs = bank.conditioning()
        noise = bank.noise_variance
    else:
        ck, cs, noise = [], [], []
        for learner in getattr(controller.bank, "learners", []):
            if not hasattr(learner, "S_"):
                continue
            koo = learner.kernel_(learner.inducing_xi_, learner.inducing_u_)
            koo[np.diag_indices_from(koo)] += learner.jitter_
            ck.append(float(np.linalg.cond(koo)))
            cs.append(float(np.linalg.cond(koo + learner.S_ / learner.noise_variance_)))
            noise.append(float(learner.noise_variance_))
    if len(ck) == 0:
        return {}
    return {"cond_koo": float(np.max(ck)), "cond_sig": float(np.max(cs)),
            "noise": float(np.median(noise))}


def _seeds(spec: str) -> tuple[str, range]:
    scenario, _, seeds = spec.partition(":")
    lo, _, hi = seeds.partition("-")
    return scenario, range(int(lo), int(hi or lo) + 1)


def run(scenarios=DEFAULT_SCENARIOS, learner: str = "afvsgp",
        learner_kwargs: dict | None = None) -> list[dict]:
    """One row per episode: :func:`run_episode`'s counts plus :func:`conditioning`
    (``learner_kwargs`` go to the filter's learners, e.g. ``{"prior": None}``)."""
    from afvsgp_gym.benchmarks.filter import run_episode

    options = {"learner_kwargs": learner_kwargs} if learner_kwargs else {}
    rows = []
    for spec in scenarios:
        scenario, seeds = _seeds(spec)
        for seed in seeds:
            res = run_episode(scenario, learner, seed, probe=conditioning, **options)
            rows.append({"scenario": scenario, "seed": seed, **res})
    return rows


def _summary(rows: list[dict]) -> list[str]:
    out = ["| scenario | episodes | violating | min h (m) | backup steps | track mean +- s.e. / "
           "max (m) | cond(K_oo) median / max | cond(K_oo + S/s2) median / max | noise var. |",
           "|---|---|---|---|---|---|---|---|---|"]
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        rs = [r for r in rows if r["scenario"] == scenario]
        tr = np.array([r["track_mean"] for r in rs])
        se = tr.std(ddof=1) / np.sqrt(len(tr)) if len(tr) > 1 else float("nan")
        ck = [r["cond_koo"] for r in rs if "cond_koo" in r]
        cs = [r["cond_sig"] for r in rs if "cond_sig" in r]
        noise = [r["noise"] for r in rs if "noise" in r]
        cond = (f"{np.median(ck):.1e} / {max(ck):.1e} | {np.median(cs):.1e} / {max(cs):.1e} | "
                f"{np.median(noise):.3g}") if ck else "- | - | -"
        out.append(f"| {scenario} | {len(rs)} | {sum(r['violations'] > 0 for r in rs)} | "
                   f"{min(r['min_h'] for r in rs):.4f} | {sum(r['fallbacks'] for r in rs):.0f} | "
                   f"{tr.mean():.3f} +- {se:.3f} / {max(r['track_max'] for r in rs):.2f} | "
                   f"{cond} |")
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=list(DEFAULT_SCENARIOS),
                        help="scenario:first-last seeds (scenarios of benchmarks.filter)")
    parser.add_argument("--learner", default="afvsgp")
    parser.add_argument("--prior", default=None,
                        help="'none' or 'std_lengthscale,std_variance' (default: the learners')")
    parser.add_argument("--json", default=None, help="write the per-episode rows here")
    args = parser.parse_args(argv)
    kwargs = None
    if args.prior == "none":
        kwargs = {"prior": None}
    elif args.prior is not None:
        from afvsgp_gym.gp.hyper import LogNormalPrior

        kwargs = {"prior": LogNormalPrior(*(float(v) for v in args.prior.split(",")))}
    rows = run(args.scenarios, args.learner, kwargs)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh)
    print("\n".join(_summary(rows)))


if __name__ == "__main__":
    main()
