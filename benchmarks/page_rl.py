"""Write docs/rl.md from the RL benchmark's results.

    python benchmarks/page_rl.py            # writes docs/rl.md
    python benchmarks/page_rl.py --check    # exit 1 if it is not what this writes

Reads ``benchmarks/results/rl_results.json`` (PPO behind the AFVSGP filter, behind the oracle
filter and with no filter: the ``rl_results.json`` that ``python benchmarks/rl_benchmark.py``
writes, runs of one machine and code merged into one file) and
``benchmarks/results/rl_results_explore005.json`` (AFVSGP agents trained behind the filter with
``online_exploration=0.05``). Each gives its ``machine``, ``date``, ``code`` and ``commands``.
"""

from __future__ import annotations

import statistics

from docgen import (
    DOCS,
    RESULTS,
    main,
    measured,
    provenance,
    read_json,
    table,
    welch_p,
    wilson,
)

#: The benchmark's command when the results were made, and the script that runs it now (the
#: results files keep the commands that made them; the page shows how to run them today).
MOVED = ("python -m afvsgp_gym.benchmarks.rl", "python benchmarks/rl_benchmark.py")

MAIN = RESULTS / "rl_results.json"
EXPLORE = RESULTS / "rl_results_explore005.json"
PAGE = DOCS / "rl.md"

NAMES = {"afvsgp": "AFVSGP filter (nominal model \"zero\")",
         "oracle": "oracle filter (true model)", "unfiltered": "no filter"}


def successes(ev: dict) -> int:
    return round(ev["success_rate"] * ev["episodes"])


def pooled(runs: list[dict], key: str) -> str:
    k = sum(successes(r[key]) for r in runs)
    n = sum(r[key]["episodes"] for r in runs)
    lo, hi = wilson(k, n)
    return f"{100 * k / n:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


def main_table(data: dict) -> list[str]:
    rows = []
    for cond, name in NAMES.items():
        runs = [r for r in data["runs"] if r["condition"] == cond]
        if not runs:
            continue
        own = [r["eval_own"] for r in runs]
        train = [r["training"] for r in runs]
        rows.append((
            f"{name}, {len(runs)} agents", pooled(runs, "eval_own"), pooled(runs, "eval_afvsgp"),
            f"**{pooled(runs, 'eval_afvsgp_kept')}**",
            f"{sum(e['episodes_with_cost'] for e in own)} of {sum(e['episodes'] for e in own)}",
            f"{statistics.fmean(e['return_mean'] for e in own):.2f}",
            f"{sum(t['cost_steps'] for t in train):,}",
            f"{sum(t['episodes_with_cost'] for t in train)} of "
            f"{sum(t['episodes'] for t in train):,}",
            f"{100 * statistics.fmean(t['final_success'] for t in train):.0f} %",
            f"{statistics.fmean(r['train_wall_s'] for r in runs) / 60:.1f} min"))
    return [table(("trained", "held-out success, own condition, fresh filter per goal (95 % CI)",
                   "behind AFVSGP, fresh filter", "behind a kept AFVSGP filter",
                   "held-out episodes with cost (own condition)", "eval. return",
                   "training cost steps", "training episodes with cost",
                   "final training success", "training wall time per run"), rows)]


def per_seed(data: dict) -> list[str]:
    rows = []
    for cond in NAMES:
        for r in sorted((r for r in data["runs"] if r["condition"] == cond),
                        key=lambda r: r["seed"]):
            rows.append((cond, r["seed"], *(f"{100 * r[k]['success_rate']:.0f} %" for k in
                                            ("eval_own", "eval_afvsgp", "eval_afvsgp_kept")),
                         r["eval_own"]["episodes_with_cost"], f"{r['training']['cost_steps']:,}"))
    return [table(("trained", "seed", "success, own", "behind AFVSGP, fresh",
                   "behind a kept AFVSGP", "held-out episodes with cost",
                   "training cost steps"), rows)]


def exploration(data: dict, other: dict) -> list[str]:
    base = [r for r in data["runs"] if r["condition"] == "afvsgp"]
    alt = [r for r in other["runs"] if r["condition"] == "afvsgp"]
    setting = other["config"].get("filter_kwargs", {})
    rows = []
    for name, runs in ((f"defaults ({len(base)} agents, the table above)", base),
                       (f"`{setting}` ({len(alt)} agents)", alt)):
        train = [r["training"] for r in runs]
        rows.append((name, pooled(runs, "eval_own"), pooled(runs, "eval_afvsgp_kept"),
                     f"{sum(t['episodes_with_cost'] for t in train)} of "
                     f"{sum(t['episodes'] for t in train):,}"))
    diffs = []
    for key, label in (("eval_own", "fresh"), ("eval_afvsgp_kept", "kept")):
        a = [r[key]["success_rate"] for r in alt]
        b = [r[key]["success_rate"] for r in base]
        diffs.append(f"{label} {100 * (statistics.fmean(a) - statistics.fmean(b)):+.1f} points "
                     f"(Welch's t-test over the agents, p = {welch_p(a, b):.2f})")
    return [table(("filter during training", "held-out success, fresh filter per goal",
                   "behind a kept AFVSGP filter", "training episodes with cost"), rows), "",
            "Difference in held-out success (the evaluation runs the default filter): "
            + "; ".join(diffs) + ".", "",
            measured(other), ""]


def build() -> dict:
    data, other = read_json(MAIN), read_json(EXPLORE)
    cfg = data["config"]
    out = [provenance("benchmarks/page_rl.py", ["benchmarks/results/rl_results.json",
                                                "benchmarks/results/rl_results_explore005.json"]),
           "",
           "# RL behind the filter",
           "",
           "PPO (Stable-Baselines3) learning `afvsgp_gym/FrankaObstacleReach-v0` behind the "
           "learned AFVSGP filter with the dynamics unknown, behind the oracle filter (the "
           "true model), and with no filter, on the same seeds. Each run trains for "
           f"{cfg['timesteps']:,} agent steps ({10 * cfg['timesteps']:,} filtered env steps) "
           f"with {cfg['n_envs']} envs in worker processes, one filter per worker that keeps "
           "learning across that worker's episodes. The final deterministic policy is then "
           f"evaluated on {cfg['eval_episodes']} held-out goals never drawn in training, "
           "(a) each goal in a fresh env and a fresh filter (which warms up again in every "
           "episode), in the training condition and behind the AFVSGP filter, and (b) behind "
           "an AFVSGP filter kept across the goals, as in training and as a deployed robot "
           f"runs it (after {cfg['kept_filter_warmup']} unrecorded episodes on other goals). "
           "Success intervals are Wilson 95 % intervals pooled over the agents' episodes; the "
           "agents differ by more than the binomial noise, so the per-seed rows matter.",
           "",
           measured(data),
           "",
           "```bash"] + [c.replace(*MOVED) for c in data.get("commands", [])] + [
           "python benchmarks/page_rl.py          # this page",
           "```", "",
           "![Training curves: return, success rate and cumulative training cost against "
           "agent steps](rl_training.png)", "",
           "## Held-out success and cost", ""]
    out += main_table(data) + ["", "Per agent:", ""] + per_seed(data) + [""]
    out += ["## Online exploration during training", "",
            "Behind the filter an agent sees the filter's online exploration (noise added "
            "where the learned action gain is uncertain, up to `online_exploration` of the "
            "half range) in its transitions. The same training behind a filter with a small "
            "constant exploration instead:", ""]
    out += exploration(data, other)
    out += [
        "## The task, and why it is built this way", "",
        "`FrankaObstacleReach-v0` is the Franka plant of the obstacle environments (hidden "
        "payload, link masses, damping, armature; the whole-arm safety spheres; cost = "
        "`h < 0` or any arm contact) reaching a goal drawn per reset past one static sphere "
        "that lies on the straight path. Success: the end-effector within 5 cm of the goal "
        "(FetchReach's tolerance), which ends the episode; at most 1250 steps (5 s).", "",
        "- **Action: a 3-D end-effector velocity command** (0.3 m/s per unit), turned into "
        "joint torques by a kinematic inner loop computed at the start of each 4 ms step and "
        "held, `tau = A(q, q') u + c(q, q')`. Seven raw torques at 250 Hz are not learnable "
        "in this budget; three velocity inputs are. Because the torque is affine in the "
        "action and held, the barrier terms stay exact and `SafetyFilter` runs on this action "
        "unchanged (the learned filter knows none of this: nominal model \"zero\").",
        "- **The agent acts at 25 Hz, the filter at 250 Hz**: `ActionRepeat(10)` sits outside "
        "`SafetyFilter`, so every inner step is filtered, and `EpisodeSafetyStats` counts "
        "cost, interventions and backups over every inner step.",
        "- **Warm-up**: with nothing known nothing is certified during the filter's warm-up "
        "(75 samples, 0.3 s). The env starts every obstacle 0.22 m from every safety sphere, "
        "more than any sphere can travel in 0.3 s under any command (a test drives the "
        "extreme commands), so no warm-up step can have cost, for a fresh filter in every "
        "evaluation episode too.",
        "- **Reward**: progress towards the goal, time and control penalties, a penalty per "
        "cost step and a success bonus. The cost penalty makes the unfiltered agent a fair "
        "baseline: it is rewarded for avoiding the obstacle, it just has no filter.",
        "- **PPO settings** (`afvsgp_gym.agents.sb3.default_algo_kwargs`): rollouts of 256 "
        "steps per env, mini-batches of 128, 10 epochs, gamma 0.98, GAE 0.95, learning rate "
        "6e-4, two layers of 64, initial action std 0.61.", "",
        "## Reading it", "",
        "- Agents trained behind the oracle filter lean on its exact, late interventions and "
        "do worse behind the learned one.",
        "- Charging the filter's corrections to the agent's reward (the shielded-RL remedy) "
        "taught the agent to stop short of the obstacle rather than to go round it; it is "
        "not an option of the package.",
        "- SAC runs through the same pipeline (`afvsgp-gym train --algo sac`) but is not "
        "tuned for this task.",
        "- `train` starts its env workers with one BLAS thread each: with a BLAS thread pool "
        "per worker, two workers on two cores run several times slower.",
        "- A trained agent ships as `docs/agents/reach_ppo_afvsgp.zip`: "
        "`afvsgp-gym evaluate --env afvsgp_gym/FrankaObstacleReach-v0 --agent "
        "docs/agents/reach_ppo_afvsgp.zip --learner afvsgp --episodes 20`.", ""]
    return {PAGE: "\n".join(out)}


if __name__ == "__main__":
    raise SystemExit(main(__doc__, build))
