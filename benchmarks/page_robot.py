"""Write the measured runs of the Franka bridge into docs/robot.md.

    python benchmarks/page_robot.py            # writes the block in docs/robot.md
    python benchmarks/page_robot.py --check    # exit 1 if it is not what this writes

Reads ``benchmarks/results/robot.jsonl`` (``python benchmarks/robot_runs.py``: one record per
run of the bridge on its MuJoCo stand-in, each with its ``machine``, ``date``, ``code`` and
load average; the last record of each label counts) and writes the block between
``<!-- robot-runs:start`` and ``<!-- robot-runs:end -->`` of the page, section "What the
simulated loop measures": the wall-clock runs, the stepped runs and the sentences that quote
them.
"""

from __future__ import annotations

from docgen import DOCS, RESULTS, cp_upper, main, measured, read_jsonl, replace_block, table

SOURCE = RESULTS / "robot.jsonl"
PAGE = DOCS / "robot.md"
BLOCK = "robot-runs"

WALL_CLOCK = ("60s-fifo", "10s-fifo", "10s-normal", "60s-fifo-self-collision",
              "10s-fifo-self-collision")
BOUNDS = ("bound-default", "bound-small", "bound-none", "bound-none-no-payload",
          "bound-default-self-collision")
#: a stepped run and the same run with the sphere kinematics and pair terms in numpy
ARM_PAIRS = (("bound-default", "bound-default-numpy-arm"),
             ("bound-default-self-collision", "bound-default-self-collision-numpy-arm"))
PERCEPTION = ("perception-exact", "perception-noise-1cm")
LEARNER = "learner-afvsgp"
LEARNER_WALL = "10s-fifo-learner-afvsgp"
#: the policies built to break the filter (robot_runs.py's ``adversarial-`` runs)
ADVERSARIAL = ("ram", *(f"swing{j}" for j in range(1, 8)), "random")
ADVERSARIAL_SEEDS = (0, 1)
COST_KINDS = (("inside", "inside an obstacle"), ("contact", "touching an obstacle"),
              ("limit", "at a joint limit"), ("self_contact", "touching itself"))
PERCENTILES = ("p50", "p90", "p99", "p99.9", "max")
#: the acceptance of a run: at most this share of deadline misses (and no step with cost)
ACCEPTED_MISSES = 0.005


def latest(recs: list[dict]) -> dict[str, dict]:
    """The last record of each label."""
    return {r["label"]: r for r in recs}


def meta(recs: list[dict]) -> dict:
    def one(key: str) -> str | None:
        return " / ".join(sorted({str(r[key]) for r in recs if r.get(key)})) or None

    return {"machine": one("machine"), "date": one("date"), "code": one("code")}


def count(n: int, of: int | None = None) -> str:
    if of is None or n == 0:
        return f"{n:,}"
    return f"{n:,} ({100 * n / of:.2g} %)"


def ms(value: float) -> str:
    return f"{value:.2f}" if value < 10 else f"{value:.0f}"


def cm(h: float | None) -> str:
    """A clearance (m) in cm, "inside" when negative."""
    if h is None:
        return "n/a"
    return f"{100 * h:.1f} cm" if h >= 0 else f"{-100 * h:.1f} cm inside"


def bound(r: dict) -> str:
    tau = r["torque_error_nm"]
    return "none" if not any(tau) else ", ".join(f"{v:g}" for v in tau)


def scheduling(r: dict) -> str:
    return f"`{r['scheduler']}`"


def stop(r: dict) -> str:
    """The stop reason, libfranka's error by its name (``... [name]``)."""
    reason = r["stop_reason"]
    if reason == "completed":
        return reason
    if reason.endswith("]") and "[" in reason:
        reason = reason[reason.rindex("[") + 1:-1]
    return f"`{reason}` after {r['steps'] / 1000:.1f} s"


def with_self(r: dict) -> str:
    """The run's label suffix when the bridge had its self-collision barriers."""
    return ", self-collision barriers" if r.get("self_collision") else ""


def wall_clock_table(runs: dict[str, dict]) -> str:
    rows = []
    for label in WALL_CLOCK:
        if label not in runs:
            continue
        r = runs[label]
        st = r["step_time_ms"]
        rows.append((f"{r['requested_seconds']:g} s" + with_self(r), scheduling(r),
                     f"{r['load_average'][0]:.2f}", f"{r['steps']:,}",
                     f"{r['rate_hz']:.1f} Hz", count(r["deadline_misses"], r["steps"]),
                     count(r["lost_commands"] or 0, r["steps"]),
                     count(r["rate_limited_steps"], r["steps"]),
                     " / ".join(ms(st[p]) for p in PERCENTILES) if st else "n/a",
                     f"{r['cost_steps']:,}", cm(r["min_h"]), stop(r)))
    return table(("run", "scheduling", "load average", "steps", "rate", "deadline misses",
                  "lost commands", "rate-limited steps",
                  "step time p50 / p90 / p99 / p99.9 / max (ms)", "steps with cost",
                  "closest clearance (measured)", "stop"), rows)


def stepped_table(runs: dict[str, dict]) -> str:
    rows = []
    for label in BOUNDS + tuple(slow for _, slow in ARM_PAIRS) + PERCEPTION:
        if label not in runs:
            continue
        r = runs[label]
        noise = r["obstacle_noise_m"]
        st = r["step_time_ms"]
        rows.append((f"`{label}`", f"{r['requested_seconds']:g} s", bound(r),
                     f"{r['payload_kg']:g} kg",
                     "exact" if not noise else f"camera, {100 * noise:g} cm noise",
                     f"{r['cost_steps']:,}", cm(r["min_true_h"]),
                     f"{r['filter_infeasible_steps']:,}", f"{r['filter_active_steps']:,}",
                     f"{ms(st['p50'])} / {ms(st['p99'])}", stop(r)))
    return table(("run", "length", "torque-error bound (Nm)", "payload the model misses",
                  "perception", "steps with cost", "closest true clearance",
                  "infeasible steps (brake)", "filter active", "step p50 / p99 (ms)",
                  "stop"), rows)


def adversarial_runs(runs: dict[str, dict]) -> list[tuple[str, int, dict, dict | None]]:
    """``(agent, seed, with the self-collision barriers, without them)`` of the runs there
    are."""
    out = []
    for agent in ADVERSARIAL:
        for seed in ADVERSARIAL_SEEDS:
            on = runs.get(f"adversarial-{agent}-{seed}")
            if on is not None:
                out.append((agent, seed, on,
                            runs.get(f"adversarial-{agent}-{seed}-no-self-collision")))
    return out


def kinds(r: dict) -> str:
    """The ticks of each kind of cost of a run ("-" without any)."""
    parts = [f"{r['cost_kinds'][key]:,} {name}" for key, name in COST_KINDS
             if r.get("cost_kinds", {}).get(key)]
    return ", ".join(parts) or "-"


def adversarial_table(runs: dict[str, dict]) -> str:
    rows = []
    for agent, seed, on, off in adversarial_runs(runs):
        rows.append((f"`{agent}`", str(seed), f"{on['cost_steps']:,}", cm(on["min_true_h"]),
                     f"{on['filter_infeasible_steps']:,}",
                     "n/a" if off is None else f"{off['cost_steps']:,}",
                     "n/a" if off is None else kinds(off), stop(on)))
    return table(("agent", "seed", "steps with cost", "closest true clearance",
                  "infeasible steps (brake)", "without self-collision barriers: steps with "
                  "cost", "without: cost by kind (ticks)", "stop"), rows)


def adversarial_sentences(runs: dict[str, dict]) -> list[str]:
    found = adversarial_runs(runs)
    if not found:
        return []
    on = [r for _, _, r, _ in found]
    off = [r for _, _, _, r in found if r is not None]
    bad_on = sum(r["cost_steps"] > 0 for r in on)
    bad_off = [r for r in off if r["cost_steps"] > 0]
    what = sorted({name for r in bad_off for key, name in COST_KINDS
                   if r.get("cost_kinds", {}).get(key)})
    return [f"Against the policies built to break the filter (stepped, "
            f"{on[0]['requested_seconds']:g} s each, the default bound and payload): with the "
            f"self-collision barriers, the bridge's default, {bad_on} of {len(on)} runs had a "
            f"step with cost (exact one-sided 95 % upper bound on the rate over such runs: "
            f"{100 * cp_upper(bad_on, len(on)):.0f} %; closest true clearance "
            f"{cm(min(r['min_true_h'] for r in on))}); "
            f"without them {len(bad_off)} of {len(off)} did"
            + (f" (the arm {' and '.join(what)})" if what else "") + ". Two seeds per policy "
            "(the swings' two first signs): evidence on the stand-in, not a guarantee."]


def outcome(r: dict) -> str:
    if r["cost_steps"] == 0:
        return f"kept every step out of the obstacle ({cm(r['min_true_h'])} clear)"
    return (f"let the arm into it ({r['cost_steps']:,} steps with cost, "
            f"{cm(r['min_true_h'])} at the deepest)")


def bound_sentences(runs: dict[str, dict]) -> list[str]:
    """What each torque-error bound did to the payload the model misses."""
    out = []
    with_payload = [runs[lb] for lb in BOUNDS if lb in runs and runs[lb]["payload_kg"] > 0]
    if with_payload:
        parts = [f"{'no bound' if bound(r) == 'none' else bound(r) + ' Nm'} {outcome(r)}"
                 for r in with_payload]
        out.append(f"With the stand-in's {with_payload[0]['payload_kg']:g} kg payload the "
                   "model does not know, " + "; ".join(parts) + ".")
    for r in (runs[lb] for lb in BOUNDS if lb in runs and runs[lb]["payload_kg"] == 0):
        out.append(f"Without the payload (the model exact but for the joint damping), "
                   f"{'no bound' if bound(r) == 'none' else bound(r) + ' Nm'} {outcome(r)}.")
    return out


def arm_sentences(runs: dict[str, dict]) -> list[str]:
    """The compiled kinematics and pair terms against their numpy path, same ticks."""
    parts = []
    for fast, slow in ARM_PAIRS:
        if fast not in runs or slow not in runs:
            continue
        a, b = runs[fast]["step_time_ms"], runs[slow]["step_time_ms"]
        parts.append(f"`{fast}` {ms(b['p50'])} -> {ms(a['p50'])} ms at the median "
                     f"({b['p50'] / a['p50']:.2f}x) and {ms(b['p99'])} -> {ms(a['p99'])} ms at "
                     f"p99 ({b['p99'] / a['p99']:.2f}x)")
    if not parts:
        return []
    return ["The compiled sphere kinematics and pair terms (`afvsgp_gym.robots._arm`, "
            "the backend switch's `\"arm\"`) against their numpy path in the same ticks "
            "(the `-numpy-arm` runs, the filter compiled in both), the step from the read to "
            "the write: " + "; ".join(parts) + "."]


def batches(recs: list[dict], label: str, last: int = 2) -> list[tuple[str, list[dict]]]:
    """The runs of ``label`` grouped by code, the ``last`` codes it ran at (newest first)."""
    groups: dict[str, list[dict]] = {}
    for r in recs:
        if r["label"] == label:
            groups.setdefault(r["code"], []).append(r)
    return list(reversed(list(groups.items())))[:last]


def repeat_sentences(recs: list[dict]) -> list[str]:
    """The wall-clock runs repeated (at the newest code, and at the code before): every
    run's misses, lost commands, median step and end, so that runs on a slower or busier
    machine are seen beside the others."""
    out = []
    for label in WALL_CLOCK:
        groups = batches(recs, label)
        if sum(len(runs) for _, runs in groups) < 2:
            continue
        r = groups[0][1][-1]
        parts = []
        for code, runs in groups:
            each = "; ".join(
                f"{count(x['deadline_misses'], x['steps'])} misses, "
                f"{x['lost_commands'] or 0:,} lost commands, step p50 "
                f"{ms(x['step_time_ms']['p50'])} ms, "
                + ("completed" if x["stop_reason"] == "completed" else f"stopped by {stop(x)}")
                for x in runs)
            parts.append(f"at `{code}`, {len(runs)} run{'s' if len(runs) > 1 else ''}: {each}")
        out.append(f"The {r['requested_seconds']:g} s run{with_self(r).replace(',', ' with')} "
                   f"at `{r['scheduler']}` (the table gives the last): " + "; ".join(parts)
                   + ".")
    return out


def failures(r: dict) -> list[str]:
    """Why a wall-clock run falls short of the acceptance (empty: it meets it)."""
    why = []
    if r["stop_reason"] != "completed":
        why.append(f"stopped by {stop(r)}")
    if r["deadline_misses"] > ACCEPTED_MISSES * r["steps"]:
        why.append(f"{count(r['deadline_misses'], r['steps'])} deadline misses")
    if r["cost_steps"]:
        why.append(f"{r['cost_steps']:,} steps with cost")
    return why


def sentences(runs: dict[str, dict], recs: list[dict]) -> list[str]:
    out = []
    verdicts = []
    for label in WALL_CLOCK:
        if label not in runs:
            continue
        r = runs[label]
        name = (f"the {r['requested_seconds']:g} s run{with_self(r).replace(',', ' with')} "
                f"at `{r['scheduler']}`")
        same = batches(recs, label, 1)[0][1]  # every run at the newest code
        if len(same) > 1:  # every run at this code, not only the last
            met = sum(not failures(x) for x in same)
            verdicts.append(f"{name} met it in {met} of its {len(same)} runs at this code")
            continue
        why = failures(r)
        verdicts.append(name + (" met it" if not why else " did not (" + ", ".join(why) + ")"))
    if verdicts:
        out.append("Against the acceptance (a run that completes with at most "
                   f"{100 * ACCEPTED_MISSES:g} % missed deadlines and no step with cost) "
                   + "; ".join(verdicts) + ".")
    long = runs.get("60s-fifo")
    if long:
        span = (f"the {long['requested_seconds']:g} s run"
                if long["stop_reason"] == "completed" else
                f"the {long['steps'] / 1000:.1f} s the {long['requested_seconds']:g} s run "
                "lasted")
        out.append(f"In {span} the rate limiter changed the filter's torque in "
                   f"{count(long['rate_limited_steps'], long['steps'])} of the steps.")
    out += bound_sentences(runs)
    out += adversarial_sentences(runs)
    out += arm_sentences(runs)
    exact, noisy = runs.get("perception-exact"), runs.get("perception-noise-1cm")
    if exact and noisy:
        out.append(f"With the camera at {100 * noisy['obstacle_noise_m']:g} cm noise the "
                   f"arm kept {cm(noisy['min_true_h'])} from the sphere "
                   f"({cm(exact['min_true_h'])} with exact perception), the brake acted in "
                   f"{noisy['filter_infeasible_steps']:,} steps where the backed-off program "
                   f"was infeasible ({exact['filter_infeasible_steps']:,} exact), and the "
                   f"step took {ms(noisy['step_time_ms']['p50'])} ms at the median "
                   f"({ms(exact['step_time_ms']['p50'])} ms exact).")
    lrn = runs.get(LEARNER)
    if lrn:
        st, ob = lrn["step_time_ms"], lrn["observe_time_ms"]
        out.append(f"With a learner (`--learner {lrn['learner']}`, stepped, "
                   f"{lrn['requested_seconds']:g} s, steps with cost: "
                   f"{lrn['cost_steps']:,}) the step from the read to the write took "
                   f"{ms(st['p50'])} ms at the median, {ms(st['p99'])} ms at p99 and "
                   f"{ms(st['max'])} ms at most, and the learning after the write "
                   f"(`observe`) {ms(ob['p50'])} ms at the median and {ms(ob['max'])} ms in "
                   "its slowest step (the learners' first fit, after the warm-up samples, in "
                   "the loop in this run).")
    wall = runs.get(LEARNER_WALL)
    if wall:
        st, ob = wall["step_time_ms"], wall["observe_time_ms"]
        fit = ("the learners' warm-up fit ran in its own process and was installed "
               f"{wall['fit_ticks']:,} ticks after the warm-up samples were in"
               if wall.get("fit_ticks") is not None else
               "the learners' warm-up fit did not come back before the run ended"
               + (f" ({wall['fit_error']})" if wall.get("fit_error") else ""))
        out.append(f"On the wall clock with the learner ({wall['requested_seconds']:g} s at "
                   f"`{wall['scheduler']}`, code `{wall['code']}`) {fit}; the loop ran "
                   f"{wall['steps']:,} steps with {count(wall['deadline_misses'], wall['steps'])}"
                   f" deadline misses and {wall['lost_commands'] or 0:,} lost commands (step "
                   f"p50 {ms(st['p50'])} ms, p99 {ms(st['p99'])} ms; `observe` p50 "
                   f"{ms(ob['p50'])} ms, at most {ms(ob['max'])} ms), "
                   + ("and completed." if wall["stop_reason"] == "completed" else
                      f"and was stopped by {stop(wall)}."))
        if lrn and lrn["step_time_ms"]["p99"] > 1.0:
            out.append(f"The stepped run's p99 step with the learner "
                       f"({ms(lrn['step_time_ms']['p99'])} ms, the learned cones of the "
                       "obstacle's pairs in the program) is above the 1 ms period: with a "
                       "learner the bridge needs a faster computer than this one.")
    return out


def build() -> dict:
    all_recs = read_jsonl(SOURCE)
    runs = latest(all_recs)
    recs = list(runs.values())
    loads = [r["load_average"][0] for r in recs]
    kernels = " / ".join(sorted({r.get("kernel") or "kernel not recorded" for r in recs}))
    # the run itself holds about one core: a load above 1.5 means other work shared them
    busy = ("other work shared the cores" if max(loads) > 1.5
            else "nothing else ran on the cores")
    block = [measured(meta(recs)) + f" {kernels}. Load average (1 min) at the end of the "
             f"runs {min(loads):.2f}-{max(loads):.2f}: {busy} (the wall-clock table gives "
             "each run's).",
             "",
             "**Wall clock** (`afvsgp-gym robot --simulate`, paced at 1 kHz): the default "
             "agent (`nominal`), learner (`none`), torque-error bound (3, 3, 3, 3, 1, 1, 1 Nm) "
             "and budget (0.9 ms), the 1 kg payload the model does not know.",
             "",
             wall_clock_table(runs),
             "",
             "**Stepped** (`realtime=False`: one tick per call, a budget of 1 s so that no "
             "step falls back; the safety figures depend on the code only, the step times "
             "are the wall clock's on this machine): the default agent and learner; the "
             "run without payload has the model exact but for the joint damping, as a "
             "payload declared to the robot would leave it.",
             "",
             stepped_table(runs),
             "",
             "**Against the policies built to break the filter** (stepped as above, the "
             "bridge's `--agent ram | swing1..swing7 | random` with `--seed`, the default "
             "bound and the 1 kg payload; the moving sphere): the runs with the "
             "self-collision barriers, the bridge's default, and without them "
             "(`--no-self-collision`).",
             "",
             adversarial_table(runs),
             "",
             " ".join(sentences(runs, all_recs) + repeat_sentences(all_recs))]
    with_pairs = [r for r in recs if r.get("self_collision")]
    if with_pairs:
        block += ["", "The wall-clock and `bound-` runs with `self-collision` in their name had "
                  "the bridge's self-collision barriers "
                  f"({with_pairs[0]['self_collision_barriers']} more barriers; the bridge's "
                  "default since the runs of the policies built to break the filter, "
                  "`--no-self-collision` leaves them out); the others ran without them."]
    text = PAGE.read_text(encoding="utf-8")
    return {PAGE: replace_block(text, BLOCK, "\n".join(block) + "\n")}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
