"""Write docs/scenes.md from the scenes sweep's records.

    python benchmarks/page_scenes.py            # writes docs/scenes.md
    python benchmarks/page_scenes.py --check    # exit 1 if it is not what this writes

Reads ``benchmarks/results/scenes.jsonl.gz``: the records of ``afvsgp-gym sweep
benchmarks/configs/scenes.toml`` (the command in ``REPRODUCE``), each with its
``code_version``, ``machine`` and ``date``.
"""

from __future__ import annotations

from acceptance_tables import learner, prior, summary
from docgen import DOCS, RESULTS, hold_memory_caveat, main, measured, provenance, read_jsonl, table
from page_adversarial import cost_cell, meta

SOURCE = RESULTS / "scenes.jsonl.gz"
PAGE = DOCS / "scenes.md"
SCENES = {"afvsgp_gym/FrankaTabletop-v0": "tabletop", "afvsgp_gym/FrankaShelf-v0": "shelf"}
FILTERS = (("oracle", None, "oracle (true model)"),
           ("afvsgp", "zero", "AFVSGP, prior \"zero\""),
           ("afvsgp", "perturbed", "AFVSGP, prior \"perturbed\""),
           (None, None, "no filter"))
REPRODUCE = """\
afvsgp-gym sweep benchmarks/configs/scenes.toml --out scenes.jsonl --workers 2
gzip -c scenes.jsonl > benchmarks/results/scenes.jsonl.gz
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
                             f"{100 * s['min_h']:+.2f}", track, f"{s['backup']:.0f}",
                             f"`{codes}`"))
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
            for name, pr, _ in FILTERS[:3]:
                group = of(cell, name, pr)
                row.append(f"{sum(r['cost_steps'] > 0 for r in group)} / {len(group)}"
                           if group else "-")
            rows.append(tuple(row))
    return rows


#: The code the page's figures stand for: its brake keeps the hold point only while the
#: obstacles stand still (earlier codes kept it regardless, or took a new one at every
#: engagement and relaxed to the mean first).
CURRENT_CODE = "2ac8a9b"


def versions(recs: list[dict]) -> list[str]:
    """Which episodes ran at which code, and why together they are what
    :data:`CURRENT_CODE` runs (a paragraph; none with one code)."""
    codes = sorted({r["code_version"] for r in recs})
    if len(codes) < 2:
        return []
    parts, moving_braked = [], 0
    for code in codes:
        group = [r for r in recs if r["code_version"] == code]
        braked = [r for r in group if r["infeasible_steps"] > 0]
        on_table = sum(scene(r) == "tabletop" for r in braked)
        if code != CURRENT_CODE:
            moving_braked += on_table
        parts.append(f"`{code}` {len(group)} (reached the brake: {len(braked)}, on the "
                     f"tabletop {on_table})")
    text = ("Episodes by code: " + "; ".join(parts) + ". Between these codes only the path "
            "of a step with no action meeting the chance constraints changed (the filter "
            "brakes at once instead of relaxing to the mean-only program, and the brake keeps "
            f"its hold point, at `{CURRENT_CODE}` only while the obstacles stand still); an "
            "episode that never reaches the brake runs alike at all of them, and so does one "
            "on the shelf, whose obstacles never move")
    if moving_braked == 0:
        text += (f", while every tabletop episode that reached the brake ran at "
                 f"`{CURRENT_CODE}`: all of them are what `{CURRENT_CODE}` runs.")
    else:
        text += (f"; {moving_braked} tabletop episodes that reached the brake ran at an "
                 "earlier code.")
    return [text, ""]


def build() -> dict:
    out = [provenance("benchmarks/page_scenes.py", ["benchmarks/results/scenes.jsonl.gz"]),
           "", "# Scenes", "",
           "The workspace scenes ([Environments](environments.md)): "
           "`afvsgp_gym/FrankaTabletop-v0` (a table plane at the mount, ten boxes, capsules "
           "and spheres drawn per reset around the reference's path, and a forearm capsule "
           "that moves in after the warm-up: 12 obstacles, 252 sphere-obstacle barriers and "
           "28 joint-limit barriers) and `afvsgp_gym/FrankaShelf-v0` (a reach into a shelf "
           "of five boxes). Full episodes (16 s, 4000 steps) behind the nominal tracker and "
           "behind the adversarial policies of [Any policy](adversarial.md), with the oracle "
           "(the true model), AFVSGP with nothing known about the dynamics (prior \"zero\") "
           "and with the robot's own model (\"perturbed\"), and without a filter. An episode "
           "has cost when some step has an obstacle barrier below zero, an arm-obstacle "
           "contact (MuJoCo's geoms) or a joint past its range or datasheet speed; contact "
           "between the arm's own links is not counted yet.", ""]
    if not SOURCE.exists():
        out += ["No results yet: run", "", "```bash", REPRODUCE, "```"]
        return {PAGE: "\n".join(out) + "\n"}
    recs = read_jsonl(SOURCE)
    out += ["## By scene, policy and filter", "",
            measured(meta(recs)) + f" {len(recs)} episodes of `benchmarks/configs/scenes.toml`."
            " `min h` is the closest approach of any safety sphere to any obstacle (cm); "
            "tracking the mean distance of the hand to the reference (m, s.e. over episodes); "
            "`backup` the steps per episode with no action meeting the chance constraints "
            "(the brake).", "", *versions(recs), *hold_memory_caveat(recs),
            table(("scene", "policy", "filter", "episodes", "with cost", "95 % bound",
                   "min h [cm]", "tracking [m] (s.e.)", "backup", "code"),
                  rows_by_filter(recs)), "",
            "## By adversarial policy", "",
            "Episodes with cost per policy (seeds of `scenes.toml`).", "",
            table(("scene", "policy", "oracle", "AFVSGP zero", "AFVSGP perturbed"),
                  rows_by_agent(recs)), "",
            "To regenerate:", "", "```bash", REPRODUCE, "```"]
    return {PAGE: "\n".join(out).rstrip("\n") + "\n"}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
