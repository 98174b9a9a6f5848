"""Write docs/adversarial.md: the filter against policies built to break it.

    python benchmarks/page_adversarial.py            # writes docs/adversarial.md
    python benchmarks/page_adversarial.py --check    # exit 1 if it is not what this writes

Reads these results files, each of one sitting on one machine:

- ``results/self_collision.jsonl.gz`` (optional): ``afvsgp-gym sweep
  benchmarks/configs/self_collision.toml`` (the suite and the tracker with today's defaults:
  the self-collision barriers on, self-contact counted; gzip the results file into it);
- ``results/adversarial.jsonl.gz``: ``afvsgp-gym sweep benchmarks/configs/adversarial.toml``;
- ``results/routes.jsonl.gz``: ``afvsgp-gym sweep benchmarks/configs/routes.toml`` (the
  class-K routes compared);
- ``results/braking_authority.json``: ``python benchmarks/braking_authority.py --json ...``;
- ``results/brake.jsonl.gz`` (optional): ``afvsgp-gym sweep benchmarks/configs/brake.toml``
  (the brake, the mean-only relaxation and the calibrated band, later code);
- ``results/adversarial_limit_margin.jsonl.gz``, ``adversarial_limit_multiplier.jsonl.gz``
  and ``adversarial_limit_mixed_ungated.jsonl.gz`` (optional): the suite's ``afvsgp`` grid at
  the code versions whose Franka envs suggested the margin, and the multiplier, on every
  joint-limit barrier, and the two mixed and adapted on every step.

To refresh them, run those commands, then ``python benchmarks/page_adversarial.py --refresh
ADVERSARIAL.jsonl ROUTES.jsonl AUTHORITY.json [BRAKE.jsonl]``: it keeps the fields the page
reads (:data:`FIELDS`), compresses the records into the results files and writes the page.
"""

from __future__ import annotations

import gzip
import json
import os
import platform
import shutil
import sys
import time

from acceptance_tables import PRIORS, learner, prior, scenario, summary
from docgen import (
    DOCS,
    RESULTS,
    hold_memory_caveat,
    main,
    measured,
    provenance,
    read_json,
    read_jsonl,
    table,
)
from self_collision_tables import (
    by_agent_rows,
    failure_lines,
    self_cell,
    suite_rows,
    tracker_rows,
)

SOURCE = RESULTS / "adversarial.jsonl.gz"
#: ``afvsgp-gym sweep benchmarks/configs/self_collision.toml``: the suite with today's
#: defaults (self-collision barriers on, self-contact counted as cost)
SELF = RESULTS / "self_collision.jsonl.gz"
ROUTES = RESULTS / "routes.jsonl.gz"
AUTHORITY = RESULTS / "braking_authority.json"
BRAKE = RESULTS / "brake.jsonl.gz"
#: Code versions of the AFVSGP episodes run again after the brake change (the filter brakes at
#: once instead of relaxing to the mean, and the brake keeps its hold point): the episodes
#: that had reached the brake and a sample of the others.
BRAKE_RERUN_CODES = ("49e78fd", "2ac8a9b", "b492550", "f6db547", "920d688")
#: the suite's AFVSGP grid with the conformal additive margin on every joint-limit band (the
#: Franka envs' suggestion at that code version)
MARGIN = RESULTS / "adversarial_limit_margin.jsonl.gz"
#: the same with the conformal multiplier on every joint-limit band (that code version's
#: suggestion, reverted)
MULTIPLIER = RESULTS / "adversarial_limit_multiplier.jsonl.gz"
#: the same with the margin on the ranges and the multiplier on the speeds, adapted on every
#: step (before ``calibration_gate``)
UNGATED = RESULTS / "adversarial_limit_mixed_ungated.jsonl.gz"
BRAKE_BLOCKS = {
    "defaults": "the paper's band (`calibration=\"off\"`; the mean-only relaxation, then "
                "the brake)",
    "no_relaxation": "no mean-only relaxation (`relax_to_mean=False`)",
    "conformal_margin": "the conformal additive margin (`calibration=\"conformal-additive\"`, "
                        "`calibration_step=1`)",
    "limit_margin": "the same margin on the 28 joint-limit barriers only (`calibration_step` 0 "
                    "for the obstacle pairs)",
    "limit_multiplier": "the conformal multiplier on the joint-limit barriers only "
                        "(`calibration=\"conformal\"`, `calibration_step` 1 std per miss, 0 "
                        "for the obstacle pairs)",
    "limit_mixed": "the margin on the 14 range barriers, the multiplier on the 14 speed "
                   "barriers (`calibration` per barrier), adapted on every step: the Franka "
                   "envs' default before `calibration_gate`",
}
TRACKER_BLOCKS = {
    "tracker_defaults": "AFVSGP, the paper's band",
    "tracker_limit_margin": "AFVSGP, the margin on the joint-limit barriers only",
    "tracker_limit_multiplier": "AFVSGP, the multiplier on the joint-limit barriers only",
    "tracker_limit_mixed": "AFVSGP, the margin on the ranges, the multiplier on the speeds, "
                           "every step (the default before the gate)",
    "tracker_oracle": "oracle (true model)",
}
PAGE = DOCS / "adversarial.md"

#: the record fields the page reads (the rest of a sweep's records is left out of the tree)
FIELDS = ("block", "config", "seed", "code_version", "machine", "date", "steps",
          "cost_steps", "violation_steps", "contact_steps", "limit_steps", "min_h",
          "infeasible_steps", "tracking_error_mean", "safe_proposals", "safe_proposals_kept",
          "filter_time_median_s", "self_contact_steps")

AGENTS = ("ram", "greedy", "swing1", "swing2", "swing3", "swing4", "swing5", "swing6",
          "swing7", "random", "untrained-ppo")
ROUTE_NAMES = {
    "R0_linear_a4": "linear `alpha_1 = 4 h` (the gains before)",
    "R1_linear_from_limits": "linear `alpha_1 = 1.3 h` (`a_1 <= A / v_max`)",
    "R2_braking": "braking curve, `A` = 5 m/s^2 (chosen)",
}


def meta(recs: list[dict]) -> dict:
    def one(key: str) -> str | None:
        values = sorted({str(r[key]) for r in recs if r.get(key)})
        return " / ".join(values) or None

    return {"machine": one("machine"), "date": one("date"), "code": one("code_version")}


def cost_cell(s: dict) -> str:
    return (f"{s['cost']} (h < 0: {s['h_eps']}, contact: {s['contact_eps']}, limits: "
            f"{s['limit_eps']})")


def label(rec: dict) -> str:
    name = learner(rec) or "unfiltered"
    return {"oracle": "oracle (true model)", "afvsgp": "AFVSGP", "none": "nominal model only",
            "unfiltered": "no filter"}.get(name, name)


def headline(recs: list[dict]) -> list[tuple]:
    rows = []
    for name in ("oracle", "afvsgp", "none", None):
        group = [r for r in recs if learner(r) == name]
        if not group:
            continue
        priors = PRIORS if name in ("afvsgp", "none") else (None,)
        for pr in priors:
            sub = [r for r in group if pr is None or prior(r) == pr]
            if sub:
                s = summary(sub)
                code = " / ".join(sorted({str(r.get("code_version")) for r in sub}))
                rows.append((label(sub[0]) + (f", prior \"{pr}\"" if pr else ""), s["n"],
                             cost_cell(s), f"{100 * s['bound']:.3g} %", f"{s['min_h']:+.4f}",
                             self_cell(sub), f"`{code}`"))
        if name == "afvsgp" and len({prior(r) for r in group}) > 1:
            s = summary(group)
            code = " / ".join(sorted({str(r.get("code_version")) for r in group}))
            rows.append(("**AFVSGP, all priors**", s["n"], cost_cell(s),
                         f"{100 * s['bound']:.3g} %", f"{s['min_h']:+.4f}", self_cell(group),
                         f"`{code}`"))
    return rows


def by_agent(recs: list[dict]) -> list[tuple]:
    rows = []
    for agent in AGENTS:
        cells = [agent]
        for name, pr in (("oracle", None), ("afvsgp", "zero"), ("afvsgp", "kinematic"),
                         ("afvsgp", "perturbed"), ("none", "zero"), (None, None)):
            group = [r for r in recs if r["config"]["agent"] == agent and learner(r) == name
                     and (pr is None or prior(r) == pr)]
            cells.append(f"{sum(r['cost_steps'] > 0 for r in group)} / {len(group)}"
                         if group else "-")
        rows.append(cells)
    return rows


def routes(recs: list[dict]) -> list[str]:
    adversarial = [r for r in recs if r["config"]["agent"] != "nominal"]
    tracker = [r for r in recs if r["config"]["agent"] == "nominal"]
    rows = []
    for block, name in ROUTE_NAMES.items():
        adv = [r for r in adversarial if r["block"].startswith(block)]
        cells = [name]
        if adv:
            s = summary(adv)
            cells += [f"{s['cost']} / {s['n']}", f"{s['min_h']:+.4f}",
                      f"{sum(r['infeasible_steps'] for r in adv)}"]
        else:
            cells += ["-", "-", "-"]
        for lrn in ("oracle", "afvsgp"):
            group = [r for r in tracker if r["block"].startswith(block) and learner(r) == lrn]
            if group:
                s = summary(group)
                cells.append(f"{s['track']:.4f} ({s['cost']} / {s['n']} with cost)")
            else:
                cells.append("-")
        oracle = [r for r in tracker if r["block"].startswith(block) and learner(r) == "oracle"]
        learned = [r for r in tracker if r["block"].startswith(block) and learner(r) == "afvsgp"]
        cells.append(f"{summary(learned)['track'] / summary(oracle)['track']:.2f}"
                     if oracle and learned else "-")
        rows.append(cells)
    return [measured(meta(recs)) + f" {len(recs)} episodes.", "",
            table(("first class-K function", "adversarial, oracle: with cost", "min h [m]",
                   "infeasible steps", "tracker, oracle: tracking [m]",
                   "tracker, AFVSGP zero: tracking [m]", "AFVSGP / oracle"), rows)]


def brake(recs: list[dict]) -> list[str]:
    agents = list(dict.fromkeys(r["config"]["agent"] for r in recs
                                if r["config"]["agent"] != "nominal"))
    rows = []
    for block, name in BRAKE_BLOCKS.items():
        group = [r for r in recs if r["block"] == block and r["config"]["agent"] != "nominal"]
        if not group:
            continue
        s = summary(group)
        rows.append((name, s["n"], cost_cell(s), f"{100 * s['bound']:.3g} %",
                     *(f"{sum(r['cost_steps'] > 0 for r in g)} / {len(g)}"
                       for a in agents
                       if (g := [r for r in group if r["config"]["agent"] == a]))))
    tracker = [r for r in recs if r["config"]["agent"] == "nominal"]
    out = [measured(meta(recs)) + f" {len(recs)} episodes.", "",
           table(("filter", "episodes", "with cost", "95 % bound", *agents), rows)]
    oracle = [r for r in tracker if r["block"] == "tracker_oracle"]
    rows = []
    for block, name in TRACKER_BLOCKS.items():
        group = [r for r in tracker if r["block"] == block]
        if group:
            s = summary(group)
            ratio = (f"{s['track'] / summary(oracle)['track']:.2f}" if oracle else "-")
            rows.append((name, s["n"], cost_cell(s), f"{s['track']:.4f} ({s['track_se']:.4f})",
                         ratio, f"{s['backup']:.1f}"))
    if rows:
        out += ["", f"Behind the nominal tracker ({len(tracker)} episodes: the three scenes, "
                "priors \"zero\" and \"kinematic\", the same seeds; tracking error where the "
                "reference is 5 cm clear of the obstacle, s.e. over episodes; `backup`: "
                "infeasible steps per episode):", "",
                table(("filter", "episodes", "with cost", "tracking [m] (s.e.)", "/ oracle",
                       "backup"), rows)]
    return out


def limit_bands(variants: list[tuple[str, list[dict]]]) -> list[str]:
    rows = []
    for pr in (*PRIORS, None):
        for name, group in variants:
            cell = [r for r in group if learner(r) == "afvsgp" and (pr is None or prior(r) == pr)]
            if cell:
                s = summary(cell)
                code = " / ".join(sorted({str(r.get("code_version")) for r in cell}))
                rows.append((pr or "**all**", name, s["n"], cost_cell(s),
                             f"{100 * s['bound']:.3g} %", f"{100 * s['min_h']:.2f}",
                             f"{s['backup']:.0f}", f"`{code}`"))
    recs = [r for _, group in variants for r in group]
    return [measured(meta(recs)) + f" {len(recs)} episodes.", "",
            table(("prior", "band on the joint limits", "episodes", "with cost", "95 % bound",
                   "min h [cm]", "infeasible steps per episode", "code"), rows)]


def authority(res: dict) -> list[str]:
    pct = res["authority_over_demand_percentiles"]
    fast = res["fast_authority_over_demand_percentiles"]
    rows = [(name, f"{100 * res['sphere_infeasible_share'][name]:.4f} %",
             f"{pct[name]['0.01%']:.2f}", f"{pct[name]['1%']:.2f}",
             f"{fast[name]['min']:.2f}", f"{fast[name]['1%']:.2f}")
            for name in res["sphere_infeasible_share"]]
    joints = res["joint_infeasible_share"]
    return [f"**Machine:** {res.get('machine', 'not recorded')}; **date:** "
            f"{res.get('date', 'not recorded')}; {res['sphere_samples']} (state, sphere, "
            f"direction) samples from {res['states']} states, {res['fast_approach_samples']} "
            "of them approaching faster than 1.5 m/s.", "",
            table(("first class-K function", "infeasible samples",
                   "authority / demand, 0.01 %", "1 %", "approach > 1.5 m/s: min", "1 %"),
                  rows), "",
            "The joint range barriers: infeasible samples per joint (of "
            f"{res['joint_samples']} states each), linear `a = 4`: "
            + ", ".join(f"{100 * v:.2g} %" for v in joints["linear a=4"])
            + "; braking curve of the datasheet's accelerations: "
            + ", ".join(f"{100 * v:.2g} %" for v in joints["braking (datasheet A_j), a=4"])
            + "."]


def codes_paragraph(recs: list[dict]) -> list[str]:
    """Why the rows come from several code versions (none when they do not)."""
    if len({r.get("code_version") for r in recs}) < 2:
        return []
    text = ("Rows of several codes: the AFVSGP rows were run again after the joint-speed "
            "barriers took the conformal multiplier, adapted only where a miss could decide "
            "the constraint (below), and the brake's give-way learned to lock joints at their "
            "range margin. The oracle, the nominal-only filter and no filter learn nothing, so "
            "the first change leaves their rows as they were; the second acts only when the "
            "brake gives way" + ("" if any(r["config"]["learner"] == "oracle"
                                            and r["infeasible_steps"] for r in recs)
                                 else " (the oracle's episodes never reach the brake)")
            + "; the filter-free row uses no brake.")
    rerun = [r for r in recs if str(r.get("code_version")) in BRAKE_RERUN_CODES
             and r["config"]["learner"] == "afvsgp"]
    if rerun:
        codes = " / ".join(f"`{c}`" for c in sorted({str(r["code_version"]) for r in rerun}))
        text += (f" The {len(rerun)} AFVSGP episodes at {codes} were run again: those that "
                 "had reached the brake (a step on which no action met the chance constraints) "
                 "when the filter stopped relaxing to the mean-only program, and again when the "
                 "brake came to keep its hold point (below), those with moving obstacles once "
                 "more when its give-way stopped closing in on other obstacles and kept a "
                 "pair 1 cm beyond its distance, and samples "
                 "of the others, whose "
                 "records came out identical: an episode that never reaches the brake runs "
                 "identically at every code.")
    none_rerun = [r for r in recs if r["config"]["learner"] == "none"
                  and str(r.get("code_version")) in BRAKE_RERUN_CODES]
    if none_rerun:
        codes = " / ".join(sorted({f"`{r['code_version']}`" for r in none_rerun}))
        text += (f" The nominal-only filter's {len(none_rerun)} episodes that reached the "
                 f"brake were run again at {codes}, with today's brake.")
    else:
        text += " The nominal-only rows were not run again."
    return [text, ""] + hold_memory_caveat(recs)


def traced(rec: dict) -> bool:
    """The episode with cost whose trace the section describes."""
    c = rec["config"]
    return (rec["cost_steps"] > 0 and rec["seed"] == 3007 and c["agent"] == "ram"
            and c["env_id"].endswith("Dynamic-v0") and prior(rec) == "zero")


def self_collision_section(recs: list[dict], old: list[dict]) -> list[str]:
    """The suite and the tracker with today's defaults (:mod:`self_collision_tables`)."""
    header, rows = by_agent_rows(recs, AGENTS)
    return [
        "## Episodes with cost",
        "",
        "With today's defaults: the self-collision barriers on (93 sphere pairs on "
        "non-adjacent links and the base, after the obstacle ones) and self-contact counted "
        "(`benchmarks/configs/self_collision.toml`); each prior with its default learner (per "
        "pair with nothing of the dynamics known, shared with the robot's own model). "
        "`before`: of the same episodes (scenario, policy, seed, prior) in the suite's first "
        "run below, those where the arm touched itself or its base, among those that "
        "recorded it.",
        "",
        measured(meta(recs)) + f" {len(recs)} episodes.",
        "",
        table(("filter", "episodes", "with cost", "95 % bound", "min h [m]",
               "self-contact before"), suite_rows(recs, old)),
        "",
        "By policy (episodes with cost / episodes, the three scenarios):",
        "",
        table(header, rows),
        "",
        *([f"The episodes with cost with the barriers on ({len(fails)}):", "", *fails, ""]
          if (fails := failure_lines([r for r in recs if r.get("self_collision")]))
          else []),
        *(["Traced (`FrankaObstacleDynamic-v0`, `ram`, seed 3007, prior \"zero\"): the "
           "self pairs between link 5's and link 7's spheres sit within a "
           "centimetre of their boundary at the ready pose (the spheres over-approximate "
           "meshes that can meet within the joint ranges) and the 12 Nm wrist joints give "
           "them little authority; with nothing of the dynamics known their learned band "
           "made the program infeasible while the `ram` policy pressed the hand towards the "
           "sphere, and the brake, whose hold point follows the arm while the obstacle "
           "moves, let the arm sag under the undeclared payload onto it.", ""]
          if any(traced(r) for r in recs) else []),
        "Behind the nominal tracker on the acceptance seeds, the self-collision barriers on "
        "and off in the same run (tracking: the mean distance of the hand to the reference, "
        "m, s.e. over episodes; `backup`: brake steps per episode; `filter`: the median of "
        "the episodes' median filter step, us):",
        "",
        table(("filter", "self-collision barriers", "episodes", "with cost", "self-contact",
               "tracking [m]", "backup", "filter [us]"), tracker_rows(recs)),
        "",
    ]


def build() -> dict:
    recs = read_jsonl(SOURCE)
    out = [provenance("benchmarks/page_adversarial.py",
                      ["benchmarks/results/self_collision.jsonl.gz",
                       "benchmarks/results/adversarial.jsonl.gz",
                       "benchmarks/results/routes.jsonl.gz",
                       "benchmarks/results/braking_authority.json"]),
           "",
           "# Any policy: the filter against policies built to break it",
           "",
           "Seeded 16 s episodes of the Franka scenarios (static, dynamic, random) with the "
           "default whole-arm filter and its joint-limit barriers, driven by the policies of "
           "`afvsgp_gym.agents.adversarial`: a stiff task-space spring that rams the hand into "
           "the nearest obstacle (`ram`), full-torque bang-bang swings of each joint "
           "(`swing1`..`swing7`), the box vertex that lowers the smallest barrier fastest under "
           "the true model (`greedy`), uniform random actions (`random`) and a freshly "
           "initialised PPO policy sampled stochastically (`untrained-ppo`). An episode *has "
           "cost* when any step has `info[\"cost\"] > 0`: an obstacle barrier `h < 0`, an "
           "arm-obstacle contact, a joint at its range stop or above its datasheet speed "
           "(`limits`), or two non-adjacent links of the robot touching (`self`, counted "
           "since the envs' `COST_VERSION` 1). The bound is the exact one-sided "
           "Clopper-Pearson 95 % upper bound on the per-episode cost rate; `min h` the "
           "closest approach to an obstacle (m).",
           ""]
    if SELF.exists():
        out += self_collision_section(read_jsonl(SELF), recs)
    out += ["## Episodes with cost, before the self-collision barriers",
           "",
           "The suite's first run, before the self-collision barriers were on by default and "
           "self-contact counted as cost: the column `with cost` counts what the cost counted "
           "then, `self-contact` the episodes (of those that recorded it) where the arm "
           "touched itself or its base.",
           "",
           measured(meta(recs)) + f" {len(recs)} episodes "
           "(`afvsgp-gym sweep benchmarks/configs/adversarial.toml`).",
           "",
           table(("filter", "episodes", "with cost", "95 % bound", "min h [m]", "self-contact",
                  "code"), headline(recs)),
           "",
           *codes_paragraph(recs),
           "By policy (episodes with cost / episodes, the three scenarios):",
           "",
           table(("policy", "oracle", "AFVSGP zero", "AFVSGP kinematic", "AFVSGP perturbed",
                  "nominal only, zero", "no filter"), by_agent(recs)),
           "",
           "By scenario, AFVSGP (all priors):",
           "",
           table(("scenario", "episodes", "with cost"),
                 [(sc, len(g), cost_cell(summary(g)))
                  for sc in ("static", "dynamic", "random")
                  if (g := [r for r in recs if learner(r) == "afvsgp" and scenario(r) == sc])]),
           ""]
    if ROUTES.exists():
        out += ["## Routes to feasibility under the torque limits", "",
                "The same oracle filter with three first class-K functions "
                "(`benchmarks/configs/routes.toml`): against the ram, the greedy policy and "
                "the swings of joints 1 and 2, and behind the nominal tracker (tracking error "
                "where the reference is 5 cm clear of the obstacle, prior \"zero\").", ""]
        out += routes(read_jsonl(ROUTES)) + [""]
    if MARGIN.exists() and MULTIPLIER.exists():
        out += ["## The band on the joint-limit barriers", "",
                "A joint's four limit barriers share one learner of its acceleration's model "
                "error. Driven through poses its data never covered, a joint's learned gain "
                "can drift several times too small with a confident std (in closed loop the "
                "filter's torque follows the state, and the gain's error hides in the drift "
                "term): an error that grows with the torque. An additive conformal margin "
                "(`\"conformal-additive\"`, step 1 noise std per miss) on every limit barrier "
                "left two swings of joint 4 one step above its datasheet speed. The conformal "
                "multiplier (`\"conformal\"`, step 1 std per miss) on every limit barrier "
                "follows the gain's error and removes those two, but it widens the range "
                "barriers' bands as well: the chance program is infeasible far more often, the "
                "mean-only relaxation then runs the range barriers on their wrong mean, and a "
                "joint sits on its stop. The default takes the multiplier on the speed "
                "barriers only (relative degree 1: no state to absorb one period's error) and "
                "the margin on the range barriers. Its row's code also has the brake lock, "
                "while it gives way, the joints held at their range margin (with the speed "
                "multiplier alone one episode had a held arm struck by the moving sphere: "
                "the retreat needed joint 4, held at its margin). Adapted on every step, the "
                "speed barriers' multipliers (the speed barriers are always in the program) "
                "also counted misses far from any limit, climbed far above `beta` behind the "
                "nominal tracker and held the joints' torque back for the rest of the episode: "
                "the tracker drifted away in some episodes ([Safety](safety.md), \"The band on "
                "the joint limits and tracking\"). The "
                "default adapts them only on the steps where a miss could decide the "
                "constraint (`calibration_gate`: its margin at the applied action below the "
                "band's width). The suite's AFVSGP grid with each:", ""]
        suite = [r for r in recs if r["block"] == "afvsgp"]
        variants = [("margin on all 28", read_jsonl(MARGIN)),
                    ("multiplier on all 28", read_jsonl(MULTIPLIER))]
        if UNGATED.exists():
            variants.append(("margin on ranges, multiplier on speeds, every step",
                             read_jsonl(UNGATED)))
        variants.append(("margin on ranges, multiplier on speeds, where a miss could "
                         "decide (default)", suite))
        out += limit_bands(variants) + [""]
    if BRAKE.exists():
        out += ["## The brake, the relaxation and the calibrated band", "",
                "AFVSGP with nothing known about the dynamics (priors \"zero\" and "
                "\"kinematic\") against the policies that defeated it most often, on the "
                "suite's seeds, with the brake that only damps when it saturates (the joint "
                "accelerations keep their direction; clipping each joint's torque apart, as "
                "the suite's first brake did, bent it through the coupled inertia and "
                "drove joint 4 to 7 rad/s while braking): the defaults, without the mean-only "
                "relaxation, with the conformal additive margin of "
                "[Calibration](calibration.md) on every barrier or on the joint-limit "
                "barriers only, with the conformal multiplier on the joint-limit barriers "
                "only, and with the margin on the range barriers and the multiplier on the "
                "speed barriers (`benchmarks/configs/brake.toml`).", ""]
        out += brake(read_jsonl(BRAKE)) + [""]
    if AUTHORITY.exists():
        out += ["## Can the torque limits meet the demand?", "",
                "Where `psi_1 = 0` a barrier approaching at `v` asks for `h'' >= a v` (linear) "
                "or `A v / (v + A / a)` (braking curve). `python benchmarks/braking_authority.py` "
                "samples states of the arm (joint angles in range, speeds within the "
                "datasheet's, payloads 0, 1 and 3 kg), every safety sphere and directions it "
                "approaches, and compares the best `h''` the torque box can make along the "
                "direction (with the drift; the curvature, >= 0, left out) with the demand: a "
                "ratio below 1 is a state where that barrier's program alone is infeasible.",
                ""]
        out += authority(read_json(AUTHORITY)) + [""]
    return {PAGE: "\n".join(out).rstrip("\n") + "\n"}


def _this_machine() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def refresh(adversarial: str, routes_file: str, authority_file: str,
            brake_file: str | None = None) -> None:
    """Keep :data:`FIELDS` of the sweeps' records, compress them into the results files.
    Records that lack ``machine`` and ``date`` (sweeps of older versions) get this machine's
    CPU and the day the results file was last written: refresh on the machine that ran it."""
    pairs = [(adversarial, SOURCE), (routes_file, ROUTES)]
    if brake_file is not None:
        pairs.append((brake_file, BRAKE))
    for src, dst in pairs:
        recs = read_jsonl(src)
        day = time.strftime("%Y-%m-%d", time.localtime(os.path.getmtime(src)))
        with gzip.open(dst, "wt", encoding="utf-8") as fh:
            for r in recs:
                r.setdefault("machine", _this_machine())
                r.setdefault("date", day)
                fh.write(json.dumps({k: r.get(k) for k in FIELDS}) + "\n")
    shutil.copyfile(authority_file, AUTHORITY)


if __name__ == "__main__":
    if len(sys.argv) in (5, 6) and sys.argv[1] == "--refresh":
        refresh(*sys.argv[2:])
        sys.argv[1:] = []
    raise SystemExit(main(__doc__, build))
