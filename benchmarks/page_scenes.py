"""Write docs/scenes.md from the scenes sweep's records.

    python benchmarks/page_scenes.py            # writes docs/scenes.md
    python benchmarks/page_scenes.py --check    # exit 1 if it is not what this writes

Reads ``benchmarks/results/scenes.jsonl.gz``: the records of ``afvsgp-gym sweep
benchmarks/configs/scenes.toml`` (the command in ``REPRODUCE``), each with its
``code_version``, ``machine`` and ``date``.
"""

from __future__ import annotations

from acceptance_tables import learner, prior, summary
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
from page_adversarial import cost_cell, meta
from self_collision_tables import self_cell

SOURCE = RESULTS / "scenes.jsonl.gz"
#: optional: the shared learner's ``scenes_*`` blocks (``benchmarks/configs/shared.toml``)
SHARED = RESULTS / "shared.jsonl.gz"
SPEED = RESULTS / "primitives.json"
PAGE = DOCS / "scenes.md"
SCENES = {"afvsgp_gym/FrankaTabletop-v0": "tabletop", "afvsgp_gym/FrankaShelf-v0": "shelf"}
FILTERS = (("oracle", None, "oracle (true model)"),
           ("afvsgp", "zero", "AFVSGP, prior \"zero\" (per pair, the default)"),
           ("afvsgp", "perturbed", "AFVSGP per pair, prior \"perturbed\""),
           ("afvsgp-shared", "perturbed", "AFVSGP shared, prior \"perturbed\" (the default)"),
           (None, None, "no filter"))
REPRODUCE = """\
afvsgp-gym sweep benchmarks/configs/scenes.toml --out scenes.jsonl --workers 2
gzip -c scenes.jsonl > benchmarks/results/scenes.jsonl.gz
afvsgp-gym sweep benchmarks/configs/shared.toml --out shared.jsonl --workers 2
gzip -c shared.jsonl > benchmarks/results/shared.jsonl.gz
python benchmarks/page_scenes.py"""


def scene(rec: dict) -> str:
    return SCENES.get(rec["config"]["env_id"], rec["config"]["env_id"])


def policy(rec: dict) -> str:
    return "tracker" if rec["config"]["agent"] == "nominal" else "adversarial"


def of(recs: list[dict], name: str | None, pr: str | None) -> list[dict]:
    return [r for r in recs if learner(r) == name and (pr is None or prior(r) == pr)]


def rows_by_filter(recs: list[dict]) -> list[tuple]:
    rows = []
    for sc in SCENES.values():
        for pol in ("tracker", "adversarial"):
            cell = [r for r in recs if scene(r) == sc and policy(r) == pol]
            for name, pr, text in FILTERS:
                group = of(cell, name, pr)
                if not group:
                    continue
                s = summary(group)
                track = (f"{s['track']:.3f} ({s['track_se']:.3f})" if pol == "tracker"
                         else "-")
                codes = " / ".join(sorted({str(r["code_version"]) for r in group}))
                rows.append((sc, pol, text, s["n"], cost_cell(s), f"{100 * s['bound']:.3g} %",
                             self_contact(group), f"{100 * s['min_h']:+.2f}", track,
                             f"{s['backup']:.0f}", f"`{codes}`"))
    return rows


def rows_pooled(recs: list[dict]) -> list[tuple]:
    """Per scene and filter, the tracker's and the adversarial policies' episodes together."""
    rows = []
    for sc in SCENES.values():
        for name, pr, text in FILTERS:
            group = of([r for r in recs if scene(r) == sc], name, pr)
            if group:
                s = summary(group)
                rows.append((sc, text, s["n"], cost_cell(s), f"{100 * s['bound']:.3g} %",
                             self_contact(group), f"{100 * s['min_h']:+.2f}"))
    return rows


def rows_by_agent(recs: list[dict]) -> list[tuple]:
    adversarial = [r for r in recs if policy(r) == "adversarial"]
    agents = list(dict.fromkeys(r["config"]["agent"] for r in adversarial))
    rows = []
    for sc in SCENES.values():
        for agent in agents:
            cell = [r for r in adversarial if scene(r) == sc and r["config"]["agent"] == agent]
            if not cell:
                continue
            row = [sc, agent]
            for name, pr, _ in FILTERS[:4]:
                group = of(cell, name, pr)
                row.append(f"{sum(r['cost_steps'] > 0 for r in group)} / {len(group)}"
                           if group else "-")
            rows.append(tuple(row))
    return rows


def versions(recs: list[dict]) -> list[str]:
    """Which episodes ran at which code (a sentence; none with one code)."""
    codes = sorted({r["code_version"] for r in recs})
    if len(codes) < 2:
        return []
    parts = [f"`{code}` {sum(r['code_version'] == code for r in recs)}" for code in codes]
    return ["Episodes by code: " + "; ".join(parts) + ".", ""]


def self_contact(group: list[dict]) -> str:
    """Episodes with self-contact (of those that record it)."""
    known = [r for r in group if "self_contact_steps" in r]
    if not known:
        return "-"
    return f"{sum(r['self_contact_steps'] > 0 for r in known)} / {len(known)}"


def failures(recs: list[dict]) -> list[str]:
    """One line per filtered episode with cost (none: a sentence saying so)."""
    bad = [r for r in recs if learner(r) is not None and r["cost_steps"] > 0]
    if not bad:
        return ["No filtered episode has cost.", ""]
    out = ["Filtered episodes with cost:", ""]
    for r in sorted(bad, key=lambda r: (scene(r), r["config"]["agent"], r["seed"])):
        pr = prior(r) if learner(r) in ("afvsgp", "afvsgp-shared") else None
        name = learner(r) + (f" ({pr})" if pr else "")
        out.append(f"- {scene(r)}, `{r['config']['agent']}` seed {r['seed']}, {name}: "
                   f"{r['cost_steps']} cost steps ({r['contact_steps']} with contact), min h "
                   f"{100 * r['min_h']:+.2f} cm, {r['infeasible_steps']} steps braking")
    return [*out, ""]


def speed_section() -> list[str]:
    """The step time against the number of primitives (``results/primitives.json``)."""
    if not SPEED.exists():
        return []
    res = read_json(SPEED)
    rows = [(r["primitives"], r["filter"], r["barriers"], f"{r['in_program']:.1f}",
             f"{1e6 * r['step_median_s']:.0f} / {1e6 * r['step_p99_s']:.0f}",
             f"{1e6 * r['env_step_median_s']:.0f} / {1e6 * r['env_step_p99_s']:.0f}")
             for r in res["rows"]]
    return ["## Step time against the number of primitives", "",
            f"**Machine:** {res['machine']}; **date:** {res['date']}; {res['calibration']}. "
            "The nominal tracker on the static scenario with its obstacle replaced by a table "
            "(a plane at the mount) and boxes, capsules and spheres in turn on three rings "
            "around the base (`afvsgp_gym.benchmarks.primitives.ring_primitives`), 21 arm "
            "spheres per primitive and 28 joint-limit barriers; the oracle and AFVSGP with the "
            "robot's own model (per-pair learners) advance in lockstep, "
            f"{res['steps']} timed steps each after the warm-up. `filter + learning` is "
            "`SafetyController.filter` + `observe`, `env.step` the wrapped step with the "
            "physics (us, median / p99).", "",
            table(("primitives", "filter", "barriers", "in the program (mean)",
                   "filter + learning [us]", "env.step [us]"), rows), "",
            "```bash", "taskset -c 0 python -m afvsgp_gym.benchmarks.primitives "
            "--json benchmarks/results/primitives.json", "python benchmarks/page_scenes.py",
            "```", ""]


def build() -> dict:
    out = [provenance("benchmarks/page_scenes.py", ["benchmarks/results/scenes.jsonl.gz",
                                                  "benchmarks/results/shared.jsonl.gz",
                                                  "benchmarks/results/primitives.json"]),
           "", "# Scenes", "",
           "The workspace scenes ([Environments](environments.md)): "
           "`afvsgp_gym/FrankaTabletop-v0` (a table plane at the mount, ten boxes, capsules "
           "and spheres drawn per reset around the reference's path, and a forearm capsule "
           "that moves in after the warm-up and yields, stopping once a safety sphere is 5 cm "
           "from it: 12 obstacles, 252 sphere-obstacle barriers, 93 self-collision barriers "
           "and 28 joint-limit barriers) and `afvsgp_gym/FrankaShelf-v0` (a reach into a "
           "shelf of five boxes). Full episodes (16 s, 4000 steps) behind the nominal tracker and "
           "behind the adversarial policies of [Any policy](adversarial.md), with the oracle "
           "(the true model), AFVSGP with nothing known about the dynamics (prior \"zero\") "
           "and with the robot's own model (\"perturbed\"), per pair and shared (the "
           "default there, [Learners](learners.md#the-shared-learner)), and without a filter. "
           "An episode has cost when some step has an obstacle barrier below zero, an arm-obstacle "
           "contact (MuJoCo's geoms) or a joint past its range or datasheet speed; contact "
           "between the arm's own links is counted beside it (the scenes' ids turn the "
           "self-collision barriers on).", ""]
    if not SOURCE.exists():
        out += ["No results yet: run", "", "```bash", REPRODUCE, "```"]
        return {PAGE: "\n".join(out) + "\n"}
    recs = read_jsonl(SOURCE)
    if SHARED.exists():
        recs += [r for r in read_jsonl(SHARED) if r["block"].startswith("scenes_")]
    out += ["## By scene, policy and filter", "",
            measured(meta(recs)) + f" {len(recs)} episodes of `benchmarks/configs/scenes.toml`"
            " (and the `scenes_*` blocks of `shared.toml`)."
            " `min h` is the closest approach of any safety sphere to any obstacle (cm); "
            "tracking the mean distance of the hand to the reference (m, s.e. over episodes); "
            "`backup` the steps per episode with no action meeting the chance constraints "
            "(the brake); `w/ self-contact` the episodes where two non-adjacent links touched "
            "(MuJoCo's geoms; part of the cost since the envs' `COST_VERSION` 1"
            + (f"; of the episodes run before it, {self_cell(old)} had any"
               if (old := [r for r in recs if not r.get("cost_version")]) else "")
            + ").", "", *versions(recs),
            *hold_memory_caveat(recs),
            table(("scene", "policy", "filter", "episodes", "with cost", "95 % bound",
                   "w/ self-contact", "min h [cm]", "tracking [m] (s.e.)", "backup", "code"),
                  rows_by_filter(recs)), "", *failures(recs),
            "Pooled over the tracker and the adversarial policies, per scene and filter:", "",
            table(("scene", "filter", "episodes", "with cost", "95 % bound",
                   "w/ self-contact", "min h [cm]"), rows_pooled(recs)), "",
            "## By adversarial policy", "",
            "Episodes with cost per policy (seeds of `scenes.toml`).", "",
            table(("scene", "policy", "oracle", "AFVSGP zero", "AFVSGP per pair, perturbed",
                   "AFVSGP shared, perturbed"),
                  rows_by_agent(recs)), "",
            "To regenerate:", "", "```bash", REPRODUCE, "```", "", *speed_section()]
    return {PAGE: "\n".join(out).rstrip("\n") + "\n"}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
