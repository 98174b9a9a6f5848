"""The tables of docs/adversarial.md's first section: the adversarial suite and the tracker
with the self-collision barriers on and self-contact counted as cost (the Franka envs'
defaults since ``COST_VERSION`` 1), from ``benchmarks/configs/self_collision.toml``'s records,
beside the suite's older records of the same seeds (cost version 0: self-contact reported,
not counted).
"""

from __future__ import annotations

import statistics

from acceptance_tables import learner, prior, summary
from docgen import cp_upper, mean_se

#: The adversarial blocks of self_collision.toml, in the order of the table.
SUITE_BLOCKS = ("oracle", "zero", "perturbed", "kinematic")
#: The tracker blocks: (barriers on, barriers off), the oracle first.
TRACKER_BLOCKS = (("tracker_oracle", "tracker_off_oracle", "exact"),
                  ("tracker", "tracker_off", "zero"),
                  ("tracker_perturbed", "tracker_off", "perturbed"))
LEARNER_LABELS = {"oracle": "oracle (true model)", "afvsgp": "AFVSGP per pair",
                  "afvsgp-shared": "AFVSGP shared"}


def self_contact(rec: dict) -> bool | None:
    """Whether the episode's arm touched itself or its base (None: not recorded)."""
    steps = rec.get("self_contact_steps")
    return None if steps is None else steps > 0


def self_cell(recs: list[dict]) -> str:
    """Episodes where the arm touched itself or its base, of those that recorded it."""
    known = [r for r in recs if self_contact(r) is not None]
    if not known:
        return "not recorded"
    return f"{sum(self_contact(r) for r in known)} of {len(known)}"


def with_cost(rec: dict) -> bool:
    """An episode with cost, self-contact counted: what ``info["cost"]`` counts from
    ``cost_version`` 1 on (for older records, without a ``cost_version``, their cost or a
    recorded self-contact)."""
    if rec.get("cost_version", 0) >= 1:
        return rec["cost_steps"] > 0
    return rec["cost_steps"] > 0 or bool(self_contact(rec))


def label(rec: dict) -> str:
    name = learner(rec)
    text = LEARNER_LABELS.get(name, name)
    return text if name == "oracle" else f"{text}, prior \"{prior(rec)}\""


def cost_cell(recs: list[dict]) -> str:
    s = summary(recs)
    n_self = sum(bool(self_contact(r)) for r in recs)
    return (f"{sum(with_cost(r) for r in recs)} (h < 0: {s['h_eps']}, contact: "
            f"{s['contact_eps']}, limits: {s['limit_eps']}, self: {n_self})")


def _key(rec: dict) -> tuple:
    c = rec["config"]
    return c["env_id"], c["agent"], int(rec["seed"]), prior(rec)


def before_cell(recs: list[dict], old: list[dict]) -> str:
    """Self-contact in the older records of the same episodes (env, policy, seed, prior) of
    the same kind of filter (the oracle, or AFVSGP per pair, the learner there)."""
    want = {_key(r) for r in recs}
    name = "oracle" if learner(recs[0]) == "oracle" else "afvsgp"
    same = [r for r in old if learner(r) == name and _key(r) in want]
    return self_cell(same) if same else "-"


def suite_rows(recs: list[dict], old: list[dict]) -> list[tuple]:
    rows = []
    for block in SUITE_BLOCKS:
        group = [r for r in recs if r["block"] == block]
        if group:
            n_cost = sum(with_cost(r) for r in group)
            rows.append((label(group[0]), len(group), cost_cell(group),
                         f"{100 * cp_upper(n_cost, len(group)):.3g} %",
                         f"{min(r['min_h'] for r in group):+.4f}", before_cell(group, old)))
    learned = [r for r in recs if r["block"] in SUITE_BLOCKS[1:]]
    if learned:
        n_cost = sum(with_cost(r) for r in learned)
        rows.append(("**AFVSGP, all priors**", len(learned), cost_cell(learned),
                     f"{100 * cp_upper(n_cost, len(learned)):.3g} %",
                     f"{min(r['min_h'] for r in learned):+.4f}", before_cell(learned, old)))
    return rows


def by_agent_rows(recs: list[dict], agents: tuple[str, ...]) -> tuple[list[str], list[tuple]]:
    blocks = [b for b in SUITE_BLOCKS if any(r["block"] == b for r in recs)]
    header = ["policy"] + [label(next(r for r in recs if r["block"] == b)) for b in blocks]
    rows = []
    for agent in agents:
        cells = [agent]
        for b in blocks:
            group = [r for r in recs if r["block"] == b and r["config"]["agent"] == agent]
            cells.append(f"{sum(with_cost(r) for r in group)} / {len(group)}" if group else "-")
        rows.append(tuple(cells))
    return header, rows


def tracker_rows(recs: list[dict]) -> list[tuple]:
    rows = []
    for on_block, off_block, pr in TRACKER_BLOCKS:
        for block, state in ((on_block, "on"), (off_block, "off")):
            group = [r for r in recs if r["block"] == block and prior(r) == pr]
            if not group:
                continue
            track, se = mean_se([float(r["tracking_error_mean"]) for r in group])
            filter_us = statistics.median(1e6 * r["filter_time_median_s"] for r in group)
            rows.append((label(group[0]), state, len(group), sum(with_cost(r) for r in group),
                         sum(bool(self_contact(r)) for r in group),
                         f"{track:.4f} ({se:.4f})",
                         f"{statistics.fmean(r['infeasible_steps'] for r in group):.1f}",
                         f"{filter_us:.0f}"))
    return rows


def failure_lines(recs: list[dict]) -> list[str]:
    """One line per episode with cost: filter, scenario, policy, seed, its cost steps by kind,
    the closest approach and the brake's steps."""
    out = []
    for r in recs:
        if not with_cost(r):
            continue
        c = r["config"]
        out.append(f"- {label(r)}, `{c['env_id'].split('/')[-1]}`, `{c['agent']}`, seed "
                   f"{r['seed']}: {r['cost_steps']} steps with cost (h < 0: "
                   f"{r['violation_steps']}, contact: {r['contact_steps']}, limits: "
                   f"{r.get('limit_steps') or 0}, self: {r.get('self_contact_steps') or 0}), "
                   f"min h {100 * r['min_h']:+.2f} cm, {r['infeasible_steps']} brake steps.")
    return out
