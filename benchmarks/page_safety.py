"""Write docs/safety.md and the README's results table from the acceptance sweep's records.

    python benchmarks/page_safety.py            # writes docs/safety.md and README.md's table
    python benchmarks/page_safety.py --check    # exit 1 if either is not what this writes

Reads ``benchmarks/results/acceptance.jsonl.gz``: the records of one sitting of
``afvsgp-gym sweep`` on one machine (the command in ``REPRODUCE``), each record carrying
its ``code_version``, ``machine`` and ``date``. To refresh it, run that command, compress the
results file to that path and run this script. The README's "Results" table (between
``<!-- results:start`` and ``<!-- results:end -->``) is written from the same records.

Optional, read when present: ``results/acceptance_limit_margin.jsonl.gz`` and
``acceptance_limit_mixed_ungated.jsonl.gz`` (the priors grid under earlier bands on the joint
limits), ``results/shared.jsonl.gz`` (``benchmarks/configs/shared.toml``'s tracker block) and
``results/heavy_recheck.jsonl.gz``.
"""

from __future__ import annotations

import math

from acceptance_tables import (
    PRIORS,
    SCENARIOS,
    learner,
    prior,
    same_tracker,
    scenario,
    select,
    summary,
    whole_arm,
)
from docgen import (
    DOCS,
    RESULTS,
    ROOT,
    hold_memory_caveat,
    main,
    measured,
    provenance,
    read_jsonl,
    replace_block,
    table,
)
from self_collision_tables import self_cell

SOURCE = RESULTS / "acceptance.jsonl.gz"
#: Code versions of the episodes run again after the brake change (the filter brakes at once
#: instead of relaxing to the mean, and the brake keeps its hold point): only the episodes
#: that had reached the brake, the others being identical at that code.
BRAKE_RERUN_CODES = ("104f9db", "2ac8a9b", "b492550", "f6db547", "da952a6",
                     "920d688")
#: optional: the priors grid at the code versions whose Franka envs suggested the conformal
#: margin on all 28 joint-limit barriers, and the margin on the ranges with the multiplier on
#: the speeds adapted on every step (before ``calibration_gate``)
#: optional: ``afvsgp-gym sweep benchmarks/configs/shared.toml`` (its tracker block), the
#: shared learner on the priors grid's first seeds
SHARED = RESULTS / "shared.jsonl.gz"
#: the adversarial suite, for the per-pair learners beside the shared one on the same seeds
ADVERSARIAL = RESULTS / "adversarial.jsonl.gz"
#: the registered scenes' grid, for the per-pair learners beside the shared one on the scenes
SCENES = RESULTS / "scenes.jsonl.gz"
SCENE_NAMES = {"afvsgp_gym/FrankaTabletop-v0": "tabletop", "afvsgp_gym/FrankaShelf-v0": "shelf"}
LIMIT_BANDS = (("margin on all 28", RESULTS / "acceptance_limit_margin.jsonl.gz"),
               ("mixed, every step", RESULTS / "acceptance_limit_mixed_ungated.jsonl.gz"))
#: the one-sided miss probability the default band promises, Phi(-2.5)
MISS_TARGET = 0.5 * math.erfc(2.5 / math.sqrt(2.0))
#: optional: ``afvsgp-gym sweep benchmarks/configs/heavy_recheck.toml`` with later code, the
#: episodes of the acceptance grids with a 2 kg payload on their own seeds
RECHECK = RESULTS / "heavy_recheck.jsonl.gz"
PAGE = DOCS / "safety.md"
README = ROOT / "README.md"

REPRODUCE = """\
afvsgp-gym sweep benchmarks/configs/acceptance.toml --out check.jsonl --workers 2
python benchmarks/acceptance_tables.py check.jsonl      # the same tables in a terminal"""

BLOCKS = {
    "priors": "the three scenarios x the three priors (nominal models), default plant",
    "plants": "randomised plants: link masses of plant_seed 1 or 2, payload 0.5 or 2 kg, "
              "joint friction 0 or 0.5 Nm, x scenarios x priors",
    "fast_obstacle": "the dynamic scenario with the obstacle at 0.25 m/s, payload 1 or 2 kg",
    "recheck_priors": "the priors grid on seeds no other grid uses",
    "fast_obstacle_seeds": "the fast obstacle on further seeds",
}


def seeds(recs: list[dict]) -> str:
    s = sorted({r["seed"] for r in recs})
    if len(s) > 1 and s[-1] - s[0] + 1 == len(s):
        return f"{s[0]}-{s[-1]}"
    return ", ".join(map(str, s))


def meta(recs: list[dict]) -> dict:
    def one(key: str) -> str | None:
        values = sorted({str(r[key]) for r in recs if r.get(key)})
        return " / ".join(values) or None

    return {"machine": one("machine"), "date": one("date"), "code": one("code_version")}


def cost_cell(s: dict) -> str:
    return (f"{s['cost']} (h < 0: {s['h_eps']}, contact: {s['contact_eps']}, limits: "
            f"{s['limit_eps']})")


def headline_rows(recs: list[dict]) -> list[tuple[str, list[dict]]]:
    return [("AFVSGP (learned model), whole arm", [r for r in recs if whole_arm(r)]),
            ("oracle (true model)", select(recs, "oracle")),
            ("nominal model only (no learning)", select(recs, "nominal_only")),
            ("AFVSGP, the paper's end-effector barrier only", select(recs, "paper_ee")),
            ("AFVSGP, point mass", select(recs, "pointmass"))]


def readme_table(recs: list[dict]) -> str:
    rows = []
    for name, group in headline_rows(recs):
        if group:
            s = summary(group)
            rows.append((name, s["n"], cost_cell(s), f"{100 * s['bound']:.2g} %",
                         f"{100 * s['min_h']:+.1f} cm",
                         self_cell(group) if "Franka" in group[0]["config"]["env_id"] else "-"))
    m = meta(recs)
    return (f"Seeded 16 s episodes of the obstacle-blind tracker behind the filter, measured "
            f"{m['date']} ([Safety evidence](docs/safety.md) has the machine, every grid and "
            "the tracking error), before self-collision barriers and self-contact as cost "
            "(the episodes, of those that recorded it, where the arm touched itself; today's "
            "defaults against policies built to break them: [Any policy](docs/adversarial.md))"
            ":\n\n"
            + table(("filter", "episodes", "with cost", "95 % bound on the cost rate",
                     "closest approach (min h)", "self-contact"), rows) + "\n")


def recheck_section(recs: list[dict], later: list[dict]) -> list[str]:
    """The 2 kg payload episodes run again with later code, each against its own earlier
    record (the same configuration and seed)."""
    before = {r["key"]: r for r in recs}
    rows = []
    for block in dict.fromkeys(r["block"] for r in later):
        for pr in PRIORS:
            now = [r for r in later if r["block"] == block and prior(r) == pr]
            then = [before[r["key"]] for r in now if r["key"] in before]
            if now and then:
                a, b = summary(then), summary(now)
                rows.append((block, pr, b["n"], cost_cell(a), cost_cell(b),
                             f"{a['track']:.4f}", f"{b['track']:.4f}"))
    return ["## Re-check of the 2 kg payload grids with later code", "",
            "The episodes of `plants` and `fast_obstacle` with the 2 kg payload, where every "
            "episode with cost above came from, run again on their own seeds "
            "(`benchmarks/configs/heavy_recheck.toml`) after the brake's fix (at saturation it "
            "only damps, with the largest share of the damping torque the torque limits admit, "
            "instead of clipping each joint's torque apart).", "",
            measured(meta(later)) + f" {len(later)} episodes.", "",
            table(("grid", "prior", "episodes", "with cost, before", "with cost, now",
                   "tracking [m], before", "now"), rows), ""]


def shared_section(recs: list[dict]) -> list[str]:
    """The shared learner (``afvsgp-shared``, :data:`SHARED`) against the per-pair learners of
    the priors grid on the same scenarios, priors and seeds."""
    if not SHARED.exists():
        return []
    everything = read_jsonl(SHARED)
    shared = [r for r in everything if r["block"] == "tracker"]
    rows = []
    for sc in SCENARIOS:
        for pr in PRIORS:
            mine = [r for r in shared if scenario(r) == sc and prior(r) == pr]
            if not mine:
                continue
            seeds_ = {r["seed"] for r in mine}
            per = [r for r in select(recs, "priors", scenario=sc, prior=pr)
                   if r["seed"] in seeds_]
            ora = select(recs, "oracle", scenario=sc, prior=same_tracker(pr))
            o = summary(ora)["track"] if ora else float("nan")
            for name, group in (("per-pair", per), ("shared", mine)):
                if group:
                    g = summary(group)
                    rows.append((sc, pr, name, g["n"], g["cost"], f"{g['min_h']:.4f}",
                                 f"{g['track']:.4f} ({g['track'] / o:.2f}x)",
                                 f"{g['backup']:.1f}", f"{g['kept']:.4f}"))
    code = " / ".join(sorted({str(r["code_version"]) for r in shared}))
    return ["## The shared learner", "",
            "`learner=\"afvsgp-shared\"` ([Learners](learners.md#the-shared-learner)): the "
            "seven joint-acceleration learners only, every obstacle pair projected onto them, "
            "behind the nominal tracker on the priors grid's scenarios and first seeds, with "
            "the priors that know the kinematics (`afvsgp-gym sweep "
            "benchmarks/configs/shared.toml`, its `tracker` block; code `" + code + "`, "
            "results/shared.jsonl.gz), beside the per-pair learners on the same seeds; "
            "tracking with its ratio to the oracle's. `SafetyFilter`'s default "
            "(`learner=\"auto\"`, [Learners](learners.md#the-shared-learner)) runs the "
            "shared learner when the prior is the robot's own model and the pairs are many: "
            "on the scenes below, and, since the self-collision barriers are on by default "
            "(114 pairs), on these scenarios too ([Any policy](adversarial.md)); these "
            "episodes ran without those barriers.", "",
            table(("scenario", "prior", "learner", "episodes", "with cost", "min h [m]",
                   "tracking [m]", "backup / episode", "kept"), rows), ""] + \
        shared_adversarial(everything) + shared_scenes(everything)


def _episode_key(rec: dict) -> tuple:
    c = rec["config"]
    return (c["agent"], c["env_id"], c["env_kwargs"].get("nominal_model"), rec["seed"])


def shared_adversarial(everything: list[dict]) -> list[str]:
    """The shared learner's ``adversarial`` block beside the per-pair learners' episodes of
    the adversarial suite (``results/adversarial.jsonl.gz``) on the same seeds and priors."""
    mine = [r for r in everything if r["block"] == "adversarial"]
    if not mine or not ADVERSARIAL.exists():
        return []
    keys = {_episode_key(r) for r in mine}
    per = [r for r in read_jsonl(ADVERSARIAL)
           if r["config"]["learner"] == "afvsgp" and _episode_key(r) in keys]
    rows = []
    for pr in PRIORS:
        for name, group in (("per-pair", per), ("shared", mine)):
            g = [r for r in group if r["config"]["env_kwargs"].get("nominal_model") == pr]
            if g:
                s = summary(g)
                rows.append((pr, name, s["n"], s["cost"], f"{s['min_h']:.4f}",
                             f"{s['backup']:.1f}"))
    codes = [" / ".join(sorted({str(r["code_version"]) for r in g})) for g in (per, mine)]
    return ["Against the adversarial policies ([Any policy](adversarial.md): the ram, the "
            "swings of every joint, random actions, the greedy policy and an untrained PPO "
            "policy, over the three scenarios), the `adversarial` block of the same config "
            f"(code `{codes[1]}`) beside the per-pair learners' episodes of the suite on the "
            f"same seeds (code `{codes[0]}`):", "",
            table(("prior", "learner", "episodes", "with cost", "min h [m]",
                   "backup / episode"), rows), ""]


def shared_scenes(everything: list[dict]) -> list[str]:
    """The shared learner's ``scenes_*`` blocks beside the per-pair learners' episodes of the
    scenes grid (``results/scenes.jsonl.gz``) on the same seeds, policies and prior."""
    mine = [r for r in everything if r["block"].startswith("scenes_")]
    if not mine or not SCENES.exists():
        return []
    keys = {_episode_key(r) for r in mine}
    per = [r for r in read_jsonl(SCENES)
           if r["config"]["learner"] == "afvsgp" and _episode_key(r) in keys]
    both = {_episode_key(r) for r in per}
    more = len(mine) - len(both)
    mine = [r for r in mine if _episode_key(r) in both]  # side by side on the same seeds
    rows = []
    for env_id, scene in SCENE_NAMES.items():
        for policies, tracker in (("tracker", True), ("adversarial", False)):
            for name, group in (("per-pair", per), ("shared", mine)):
                g = [r for r in group if r["config"]["env_id"] == env_id
                     and (r["config"]["agent"] == "nominal") == tracker]
                if not g:
                    continue
                s = summary(g)
                rows.append((scene, policies, name, s["n"], s["cost"],
                             sum((r.get("self_contact_steps") or 0) > 0 for r in g),
                             f"{s['min_h']:.4f}", f"{s['track']:.4f}" if tracker else "-",
                             f"{s['backup']:.1f}"))
    codes = [" / ".join(sorted({str(r["code_version"]) for r in g})) for g in (per, mine)]
    return ["On the registered scenes ([Scenes](scenes.md): the tabletop's table, clutter "
            "and moving forearm; the shelf) with the robot's own model as the prior "
            "(\"perturbed\"), the tracker and the adversarial policies on the scenes grid's "
            f"seeds, the `scenes_*` blocks of the same config (code `{codes[1]}`) beside the "
            f"per-pair learners' episodes of that grid (code `{codes[0]}`); `self-contact`: "
            "episodes where two non-adjacent links touched"
            + (f" ({more} more episodes of the shared learner on later seeds: "
               "[Scenes](scenes.md))" if more else "") + ":", "",
            table(("scene", "policies", "learner", "episodes", "with cost", "self-contact",
                   "min h [m]", "tracking [m]", "backup / episode"), rows), ""]


def limit_band_section(recs: list[dict]) -> list[str]:
    """The priors grid's tracking under each band on the joint-limit barriers the Franka envs
    have suggested (the files of :data:`LIMIT_BANDS` that exist, and the default's)."""
    variants = [(name, read_jsonl(path)) for name, path in LIMIT_BANDS if path.exists()]
    if not variants:
        return []
    variants.append(("default: mixed, where a miss could decide", recs))
    rows = []
    for sc in SCENARIOS:
        for pr in PRIORS:
            ora = select(recs, "oracle", scenario=sc, prior=same_tracker(pr))
            o = summary(ora)["track"] if ora else float("nan")
            cells = [sc, pr]
            for _, group in variants:
                g = select(group, "priors", scenario=sc, prior=pr)
                if not g:
                    cells.append("-")
                    continue
                s = summary(g)
                worst = max(r["tracking_error_mean"] for r in g)
                cells.append(f"{s['track']:.4f} ({s['track'] / o:.2f}x), worst {worst:.3f}")
            rows.append(tuple(cells))
    codes = [" / ".join(sorted({str(r["code_version"]) for r in select(g, "priors")}))
             for _, g in variants]
    return ["## The band on the joint limits and tracking", "",
            "Mean tracking error of the priors grid (same seeds), its ratio to the oracle's "
            "and the worst episode's mean, with each band the Franka envs have suggested on "
            "the 28 joint-limit barriers ([Any policy](adversarial.md), \"The band on the "
            "joint-limit barriers\"): the conformal margin on all of them; the margin on the "
            "range barriers and the multiplier on the speed barriers, adapted on every step; "
            "the same adapted only where a miss could decide the constraint (the default). "
            "Codes: " + ", ".join(f"{n} `{c}`" for (n, _), c in zip(variants, codes,
                                                                    strict=True)) + ".", "",
            table(("scenario", "prior", *(n for n, _ in variants)), rows), ""]


def calibration_section(recs: list[dict]) -> list[str]:
    """Per scenario and prior of the priors grid: the learned band's one-sided miss rate
    against its eq. 48 samples and against the exact model error, and its coverages (issue
    43's acceptance cells); nothing for records without the calibration counts."""
    rows, within, cells = [], 0, 0
    ungated = LIMIT_BANDS[1][1]
    variants = [("default", recs)] + ([("every step", read_jsonl(ungated))]
                                      if ungated.exists() else [])
    for sc in SCENARIOS:
        for pr in PRIORS:
            for name, source in variants:
                row = _calibration_row(source, sc, pr)
                if row is None:
                    continue
                if name == "default":
                    cells += 1
                    within += row[1] <= 1.5 * MISS_TARGET
                rows.append((sc, pr, name, *row[0]))
    if not rows:
        return []
    return ["## The chance constraint on these episodes", "",
            "The learned band each constraint used (`info[\"delta_b_lower\"]`) against the "
            "eq. 48 sample of the same step (`miss`) and against the exact model error (`true "
            "miss`), over every (barrier, step) pair in the program of the priors grid's "
            "episodes; the promise is a one-sided miss rate of "
            f"{100 * MISS_TARGET:.2f} % (beta = 2.5), and a calibrated Gaussian band covers "
            "68.3 / 95.4 / 99.7 % within 1 / 2 / 3 std ([Calibration](calibration.md)). The "
            "default keeps the paper's band on the obstacle pairs and corrects the joint "
            "limits' band only where a miss could decide the constraint; counted over every "
            "step its misses are those of the uncorrected band far from binding, where they "
            "change no decision, which is why they exceed the correction adapted on every step "
            "(`every step`, the code before; its tracking above). The rate on the steps the "
            "gate selects is not among the episode counts. Cells of the default within 1.5x "
            f"of the promise: {within} of {cells}.", "",
            table(("scenario", "prior", "band on the joint limits", "episodes", "scored pairs",
                   "miss", "true miss", "coverage 1 / 2 / 3 std"), rows), ""]


def _calibration_row(recs: list[dict], sc: str, pr: str) -> tuple[tuple, float] | None:
    """The calibration cells of one scenario and prior of the priors grid, and its miss rate
    (None without counts)."""
    group = [r for r in select(recs, "priors", scenario=sc, prior=pr)
             if r.get("calibration_samples")]
    if not group:
        return None
    n = sum(r["calibration_samples"] for r in group)
    miss = sum(r["calibration_misses"] for r in group) / n
    n_true = sum(r.get("true_band_samples") or 0 for r in group)
    true = (sum(r.get("true_band_misses") or 0 for r in group) / n_true if n_true
            else float("nan"))
    cov = [sum(r[f"calibration_within_{k}std"] for r in group) / n for k in (1, 2, 3)]
    return (len(group), n, f"{100 * miss:.2f} %", f"{100 * true:.2f} %",
            " / ".join(f"{100 * c:.1f} %" for c in cov)), miss


def build() -> dict:
    recs = read_jsonl(SOURCE)
    arm = [r for r in recs if whole_arm(r)]
    arm_blocks = list(dict.fromkeys(r["block"] for r in arm))
    out = [provenance("benchmarks/page_safety.py", ["benchmarks/results/acceptance.jsonl.gz"]),
           "",
           "# Safety evidence",
           "",
           "Seeded closed-loop episodes (16 s, 4000 steps each) of the nominal tracker, which "
           "ignores the obstacles, behind the safety filter. An episode *has cost* when any of "
           "its steps has `info[\"cost\"] > 0`: some obstacle barrier `h < 0`, an "
           "arm-obstacle contact, or a joint at its range stop or above its datasheet speed "
           "(`limits`). The bound is the exact one-sided Clopper-Pearson 95 % upper bound on the "
           "per-episode cost rate; `min h` the closest approach of any safety sphere to the "
           "obstacle over the episodes (m).",
           "",
           "These episodes ran before the self-collision barriers were on by default and the "
           "arm touching itself or its base counted as cost (the envs' `COST_VERSION` 1): "
           f"of the whole-arm AFVSGP episodes that recorded it, {self_cell(arm)} had "
           "self-contact. The tracker with today's defaults, barriers on and off in one run, "
           "and the policies built to break them: [Any policy](adversarial.md).",
           "",
           measured(meta(recs)) + f" {len(recs)} episodes.",
           "",
           "## Episodes with cost",
           ""]
    rows = []
    for name, group in headline_rows(recs)[:1]:
        s = summary(group)
        rows.append((f"**{name}**", s["n"], f"**{cost_cell(s)}**", f"{s['bound']:.4f}",
                     f"{s['min_h']:+.4f}"))
    for block in arm_blocks:
        group = [r for r in arm if r["block"] == block]
        s = summary(group)
        rows.append((f"of which `{block}` (seeds {seeds(group)})", s["n"], cost_cell(s),
                     f"{s['bound']:.4f}", f"{s['min_h']:+.4f}"))
    zero = [r for r in arm if prior(r) == "zero"]
    if zero:
        s = summary(zero)
        rows.append(("of which nominal model \"zero\" (nothing known)", s["n"], cost_cell(s),
                     f"{s['bound']:.4f}", f"{s['min_h']:+.4f}"))
    for name, group in headline_rows(recs)[1:]:
        if group:
            s = summary(group)
            rows.append((name, s["n"], cost_cell(s), f"{s['bound']:.4f}", f"{s['min_h']:+.4f}"))
    out += [table(("filter", "episodes", "with cost", "95 % bound", "min h [m]"), rows), ""]
    several = len({r.get("code_version") for r in recs}) > 1

    def code(block: str) -> str:
        if not several:
            return ""
        group = [r for r in recs if r["block"] == block]
        return " (code `" + " / ".join(sorted({str(r["code_version"]) for r in group})) + "`)"

    out += ["The grids (`afvsgp-gym sweep` blocks):", ""]
    out += [f"- `{b}`: {BLOCKS.get(b, 'see its config')}{code(b)}." for b in arm_blocks]
    out += ["- `oracle`: the filter with the true model, behind the trackers of the priors "
            "\"zero\" and \"perturbed\", on the priors grid's scenarios and seeds"
            f"{code('oracle')}.",
            "- `nominal_only`: the filter without learning (`learner=\"none\"`)"
            f"{code('nominal_only')}.",
            "- `paper_ee`: AFVSGP protecting only the paper's end-effector sphere "
            "(`safety_spheres=\"ee\"`): no `h < 0`, but the rest of the arm can touch the "
            f"obstacle, which is why the whole arm is the default{code('paper_ee')}.",
            f"- `pointmass`: `PointMassObstacle-v0`{code('pointmass')}.", ""]
    if several:
        rerun = sorted({str(r["code_version"]) for r in recs
                        if str(r["code_version"]) in BRAKE_RERUN_CODES})
        band = sorted({str(r["code_version"]) for r in recs if r["block"] == "priors"}
                      - set(rerun))
        text = "Blocks of several codes."
        if rerun:
            n = sum(str(r["code_version"]) in rerun for r in recs)
            text += (f" The {n} episodes at `{' / '.join(rerun)}` were run again after the "
                     "grid: those that had reached the brake (a step on which no action met the "
                     "chance constraints) when the filter stopped relaxing to the mean-only "
                     "program, and again when the brake came to keep its hold point (below), "
                     "those with moving obstacles once more when its give-way stopped closing "
                     "in on other obstacles and kept a pair 1 cm beyond its distance, "
                     "and samples of the others, whose records came out identical: an episode "
                     "that never reaches the brake runs identically at every code.")
        if band:
            text += (f" The other learning episodes ran at `{' / '.join(band)}`, after the band "
                     "on the joint limits changed (\"The band on the joint limits and "
                     "tracking\" below); the oracle and the nominal-only filter learn nothing "
                     "and the point mass has no joint limits, so that change does not touch "
                     "their blocks.")
        out += [text, ""] + hold_memory_caveat(recs)

    out += ["## Tracking against the oracle", "",
            "Mean tracking error where the reference is at least 5 cm clear of the obstacle "
            "(`info[\"reference_h\"] >= 0.05`), over the episodes of the priors grid (s.e.: "
            "standard error over episodes), against the oracle filter behind the same tracker "
            "on the same seeds (the priors \"zero\" and \"kinematic\" use a Jacobian-transpose "
            "PD tracker, \"perturbed\" the inverse dynamics of its nominal model). `backup`: "
            "steps per episode on which no action met the chance constraints; `kept`: share of "
            "the proposals safe with a 2 m/s^2 true margin that the filter passed unchanged.",
            ""]
    rows = []
    for sc in SCENARIOS:
        for pr in PRIORS:
            group = select(recs, "priors", scenario=sc, prior=pr)
            if not group:
                continue
            s = summary(group)
            ora = select(recs, "oracle", scenario=sc, prior=same_tracker(pr))
            o = summary(ora)["track"] if ora else None
            rows.append((sc, pr, s["n"], s["cost"], f"{s['min_h']:.4f}",
                         f"{s['track']:.4f} ({s['track_se']:.4f})",
                         f"{o:.4f}" if o else "-", f"**{s['track'] / o:.2f}**" if o else "-",
                         f"{s['backup']:.1f}", f"{s['kept']:.4f}"))
    out += [table(("scenario", "prior", "episodes", "with cost", "min h [m]",
                   "tracking [m] (s.e.)", "oracle [m]", "ratio", "backup / episode", "kept"),
                  rows), ""]
    rows = []
    for pr in PRIORS:
        group = select(recs, "priors", prior=pr)
        if not group:
            continue
        s = summary(group)
        ora = select(recs, "oracle", prior=same_tracker(pr))
        ratio = f"{s['track'] / summary(ora)['track']:.2f}" if ora else "-"
        rows.append((pr, s["n"], s["cost"], f"{s['track']:.4f} ({s['track_se']:.4f})", ratio,
                     f"{s['backup']:.1f}", f"{s['kept']:.4f}"))
    out += ["Per prior, over the three scenarios:", "",
            table(("prior", "episodes", "with cost", "tracking [m] (s.e.)", "/ oracle",
                   "backup / episode", "kept"), rows), ""]

    rows = []
    for block in [b for b in arm_blocks if b != "priors"]:
        for pr in PRIORS:
            group = select(recs, block, prior=pr)
            if group:
                s = summary(group)
                rows.append((block, pr, s["n"], s["cost"], f"{s['min_h']:.4f}",
                             f"{s['track']:.4f}", f"{s['backup']:.1f}", f"{s['kept']:.4f}"))
    if rows:
        out += ["## Randomised plants, the fast obstacle, further seeds", "",
                table(("grid", "prior", "episodes", "with cost", "min h [m]", "tracking [m]",
                       "backup / episode", "kept"), rows), ""]
    plants = select(recs, "plants")
    if plants:
        rows = []
        for key, values in (("friction", (0.0, 0.5)), ("payload_mass", (0.5, 2.0))):
            for v in values:
                group = [r for r in plants if r["config"]["env_kwargs"].get(key) == v]
                if group:
                    s = summary(group)
                    rows.append((f"`{key}` = {v}", s["n"], s["cost"], f"{s['track']:.3f}"))
        out += ["The randomised plants by factor:", "",
                table(("plant", "episodes", "with cost", "tracking [m]"), rows), ""]

    rows = [(f"end-effector sphere only, {sc}", select(recs, "paper_ee", scenario=sc))
            for sc in ("static", "dynamic")] + [("point mass", select(recs, "pointmass"))]
    rows = [(name, summary(g)) for name, g in rows if g]
    if rows:
        out += ["## The paper's end-effector barrier and the point mass", "",
                table(("filter", "episodes", "with h < 0", "min h [m]", "tracking [m]",
                       "with an arm contact"),
                      [(n, s["n"], s["h_eps"], f"{s['min_h']:.4f}", f"{s['track']:.4f}",
                        s["contact_eps"]) for n, s in rows]), ""]

    out += limit_band_section(recs)
    out += shared_section(recs)
    out += calibration_section(recs)
    if RECHECK.exists():
        out += recheck_section(recs, read_jsonl(RECHECK))
    learners = sorted({learner(r) for r in recs})
    out += ["## Reproduce", "",
            "```bash", REPRODUCE, "python benchmarks/page_safety.py                     # "
            "this page, from benchmarks/results/acceptance.jsonl.gz", "```", "",
            f"Learners in the file: {', '.join(learners)}. Every episode is one task in a "
            "fresh environment and filter seeded with its seed, so the records are the same "
            "whatever the number of workers or their order, and an interrupted sweep resumes "
            "where it stopped. Each config's header says what it covers.", "",
            "## Which numbers reproduce where", "",
            "A sweep is deterministic on one machine: re-running it gives the same records bit "
            "for bit, timing aside. On another CPU, BLAS or MuJoCo version the closed loop, "
            "which amplifies rounding differences of 1e-13 through online learning, follows "
            "other trajectories: per-episode `min h`, tracking errors and backup counts differ "
            "there. Compare the counts of episodes with cost and their bounds, and the means "
            "within their standard errors.", "",
            "## What this does not show", "",
            "- No cost in these episodes is a measurement, not a guarantee: the bound above is "
            "what the episodes allow, for these scenarios.",
            "- Nothing is certified before a learner has seen a region. With a zero nominal "
            "model the filter cannot act during its warm-up; the scenarios keep the obstacles "
            "away then.",
            "- When no action meets the chance constraints the filter applies the "
            "environment's brake, which removes kinetic energy, holds the arm and gives way "
            "to a moving obstacle within 10 cm, but certifies nothing: "
            "giving way can lead into another obstacle, and a retreat that needs a joint held "
            "at its range margin is carried by the other joints only, if they can.",
            "- The oracle takes the true model's joint friction at u = 0; with friction it is "
            "not an exact oracle (`oracle_terms=\"true_robust\"` bounds friction; "
            "`benchmarks/configs/oracle_friction*.toml` measure both).",
            "- Two obstacles (42 barriers, `benchmarks/configs/two_obstacles.toml`) track worse "
            "and brake more often than one.", ""]
    page = "\n".join(out)
    readme = replace_block(README.read_text(encoding="utf-8"), "results", readme_table(recs))
    return {PAGE: page, README: readme}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
