"""Safety tables of a sweep's records (the acceptance configurations of benchmarks/configs).

    afvsgp-gym sweep benchmarks/configs/acceptance.toml --out acceptance.jsonl
    python benchmarks/acceptance_tables.py acceptance.jsonl

``benchmarks/page_safety.py`` builds the documentation's safety page from these functions.

Episodes with cost, the exact Clopper-Pearson 95 % upper bound on the per-episode cost rate,
min h, mean tracking error with its standard error over episodes, the ratio to the oracle's on
the same scenarios and seeds behind the same tracker (the nominal tracker is a Jacobian-transpose
PD with the priors "zero" and "kinematic" and the inverse dynamics of the nominal model with
"perturbed", so each prior is compared with the oracle run with a prior of its tracker), backup
(infeasible) steps per episode and the share of safe proposals kept, per block, scenario and
prior.
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Iterable

from docgen import cp_upper, mean_se, read_jsonl

SCENARIOS = ("static", "dynamic", "random")
PRIORS = ("zero", "kinematic", "perturbed")


def scenario(rec: dict) -> str:
    env = rec["config"]["env_id"]
    return next((s for s in SCENARIOS if s.capitalize() in env), env.split("/")[-1])


def prior(rec: dict) -> str:
    return rec["config"]["env_kwargs"].get("nominal_model", "zero")


def same_tracker(pr: str) -> str:
    """The oracle's prior with the same nominal tracker as ``pr`` (the oracle filter itself
    uses the true model; the prior only chooses the tracker)."""
    return "perturbed" if pr in ("perturbed", "exact") else "zero"


def summary(recs: list[dict]) -> dict:
    tracked = [float(r["tracking_error_mean"]) for r in recs
               if r.get("tracking_error_mean") is not None]
    track, track_se = mean_se(tracked) if tracked else (float("nan"), float("nan"))
    safe = sum(r["safe_proposals"] for r in recs)
    return {
        "n": len(recs),
        "cost": sum(r["cost_steps"] > 0 for r in recs),
        "bound": cp_upper(sum(r["cost_steps"] > 0 for r in recs), len(recs)),
        "min_h": min(r["min_h"] for r in recs),
        "track": track,
        "track_se": track_se,
        "backup": statistics.fmean(r["infeasible_steps"] for r in recs),
        "kept": sum(r["safe_proposals_kept"] for r in recs) / safe if safe else 1.0,
        "contact_eps": sum(r["contact_steps"] > 0 for r in recs),
        "h_eps": sum(r["violation_steps"] > 0 for r in recs),
        "limit_eps": sum((r.get("limit_steps") or 0) > 0 for r in recs),
    }


def learner(rec: dict) -> str:
    return rec["config"]["learner"]


def whole_arm(rec: dict) -> bool:
    """An AFVSGP episode of a Franka env with the default whole-arm spheres."""
    return (learner(rec) == "afvsgp" and "Franka" in rec["config"]["env_id"]
            and rec["config"]["env_kwargs"].get("safety_spheres", "arm") == "arm")


def select(recs: Iterable[dict], block: str, **where) -> list[dict]:
    """The records of ``block`` (the oracle's: of learner "oracle", in whichever block; the
    whole-arm blocks': of the other learners), optionally of one scenario and prior."""
    if block == "oracle":
        out = [r for r in recs if learner(r) == "oracle"]
    else:
        out = [r for r in recs if r["block"] == block and learner(r) != "oracle"]
    if "scenario" in where:
        out = [r for r in out if scenario(r) == where["scenario"]]
    if "prior" in where:
        out = [r for r in out if prior(r) == where["prior"]]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results")
    recs = read_jsonl(parser.parse_args().results)
    versions = sorted({r["code_version"] for r in recs})
    print(f"{len(recs)} records, code {', '.join(versions)}\n")

    arm = [r for r in recs if whole_arm(r)]
    arm_blocks = list(dict.fromkeys(r["block"] for r in arm))  # in the order of the records
    zero = [r for r in arm if prior(r) == "zero"]
    print("| filter | episodes | with cost | 95 % bound | min h [m] |\n|---|---|---|---|---|")
    by_block = [(f"of which block {b}", [r for r in arm if r["block"] == b])
                for b in arm_blocks] if len(arm_blocks) > 1 else []
    for name, group in (("AFVSGP, whole arm", arm), *by_block, ("of which prior zero", zero),
                        ("oracle", select(recs, "oracle")),
                        ("nominal only", select(recs, "nominal_only")),
                        ("AFVSGP, end-effector sphere only", select(recs, "paper_ee")),
                        ("AFVSGP, point mass", select(recs, "pointmass"))):
        if group:
            s = summary(group)
            print(f"| {name} | {s['n']} | {s['cost']} (h<0: {s['h_eps']}, contact: "
                  f"{s['contact_eps']}, limits: {s['limit_eps']}) | {s['bound']:.4f} | "
                  f"{s['min_h']:.4f} |")

    if select(recs, "priors"):
        priors_tables(recs)
    other = [b for b in arm_blocks if b != "priors"]
    if not other and not any(r.get("block") in ("paper_ee", "pointmass") for r in recs):
        return  # a sweep of the priors grid only (e.g. benchmarks/configs/recheck.toml)
    print("\n| block | prior | episodes | with cost | min h [m] | tracking [m] | backup / episode "
          "| kept |\n|---|---|---|---|---|---|---|---|")
    for block in other:
        for pr in PRIORS:
            if not select(recs, block, prior=pr):
                continue
            s = summary(select(recs, block, prior=pr))
            print(f"| {block} | {pr} | {s['n']} | {s['cost']} | {s['min_h']:.4f} | "
                  f"{s['track']:.4f} | {s['backup']:.1f} | {s['kept']:.4f} |")
    plants = select(recs, "plants")
    factors = (("friction", (0.0, 0.5)), ("payload_mass", (0.5, 2.0))) if plants else ()
    for key, values in factors:
        parts = []
        for v in values:
            s = summary([r for r in plants if r["config"]["env_kwargs"].get(key) == v])
            parts.append(f"{key} {v}: {s['n']} episodes, {s['cost']} with cost, tracking "
                         f"{s['track']:.3f} m")
        print("; ".join(parts))

    rows = [(f"end-effector, {sc}", select(recs, "paper_ee", scenario=sc))
            for sc in ("static", "dynamic")] + [("point mass", select(recs, "pointmass"))]
    rows = [(name, sel) for name, sel in rows if sel]  # blocks the sweep did not run: no row
    if rows:
        print("\n| filter | episodes | with h < 0 | min h [m] | tracking [m] | with an arm "
              "contact |\n|---|---|---|---|---|---|")
    for name, sel in rows:
        s = summary(sel)
        print(f"| {name} | {s['n']} | {s['h_eps']} | {s['min_h']:.4f} | {s['track']:.4f} | "
              f"{s['contact_eps']} |")


def priors_tables(recs: list[dict]) -> None:
    """Per scenario and prior of the priors grid, against the oracle behind the same tracker;
    then per prior over the three scenarios."""
    print("\n| scenario | prior | episodes | with cost | 95 % bound | min h [m] | tracking [m] "
          "(s.e.) | oracle tracking [m] | ratio | backup / episode | kept |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for sc in SCENARIOS:
        for pr in PRIORS:
            s = summary(select(recs, "priors", scenario=sc, prior=pr))
            ora = select(recs, "oracle", scenario=sc, prior=same_tracker(pr))
            ratio, ora_track = "-", "-"
            if ora:
                o = summary(ora)["track"]
                ratio, ora_track = f"{s['track'] / o:.2f}", f"{o:.4f}"
            print(f"| {sc} | {pr} | {s['n']} | {s['cost']} | {s['bound']:.3f} | "
                  f"{s['min_h']:.4f} | {s['track']:.4f} ({s['track_se']:.4f}) | "
                  f"{ora_track} | {ratio} | {s['backup']:.1f} | {s['kept']:.4f} |")
        for pr in ("zero", "perturbed"):
            ora_recs = select(recs, "oracle", scenario=sc, prior=pr)
            if not ora_recs:
                continue
            ora = summary(ora_recs)
            print(f"| {sc} | oracle ({pr}'s tracker) | {ora['n']} | {ora['cost']} | "
                  f"{ora['bound']:.3f} | {ora['min_h']:.4f} | {ora['track']:.4f} "
                  f"({ora['track_se']:.4f}) | | | {ora['backup']:.0f} | {ora['kept']:.4g} |")

    print("\n| prior (all three scenarios) | episodes | with cost | tracking [m] (s.e.) | / oracle "
          "| backup / episode | kept |\n|---|---|---|---|---|---|---|")
    for pr in PRIORS:
        s = summary(select(recs, "priors", prior=pr))
        ora = select(recs, "oracle", prior=same_tracker(pr))
        ratio = f"{s['track'] / summary(ora)['track']:.2f}" if ora else "-"
        print(f"| {pr} | {s['n']} | {s['cost']} | {s['track']:.4f} ({s['track_se']:.4f}) | "
              f"{ratio} | {s['backup']:.1f} | {s['kept']:.4f} |")


if __name__ == "__main__":
    main()
