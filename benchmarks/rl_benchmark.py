"""RL benchmark: an agent learning FrankaObstacleReach-v0 behind the AFVSGP filter, behind
the oracle filter and with no filter (same seeds), its training cost and held-out success.

One command runs everything (docs/rl.md has the results and the design; it needs the rl
extra and runs from the repository's root)::

    python benchmarks/rl_benchmark.py          # full: 3 seeds x 3 conditions, 500k env steps
    python benchmarks/rl_benchmark.py --quick  # the pipeline in minutes (not the result)

(it was ``python -m afvsgp_gym.benchmarks.rl`` before it left the installed package).

For every condition and seed it trains with :func:`afvsgp_gym.agents.sb3.train` (two envs in
``SubprocVecEnv`` workers, one filter per worker, nominal model "zero"), then evaluates the
final deterministic policy on held-out goals (reset seeds 10000...) three times: in its
training condition and behind the AFVSGP filter, each episode in a fresh env and filter (the
convention of ``afvsgp-gym evaluate``: the filter warms up in every episode), and behind an
AFVSGP filter kept across the episodes as in training (after 10 unrecorded episodes on other
goals: a filter that has been running, as a deployed one would be). It writes
``rl_results.json`` (per-run curves binned by agent steps, evaluation summaries, wall times)
and ``rl_table.md`` under ``--out``, the figure ``rl_training.png`` (return, success rate and
cumulative training cost against agent steps; mean over seeds, band = min..max) and, for the
full run, the best AFVSGP-filtered agent as ``docs/agents/reach_ppo_afvsgp.zip``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from afvsgp_gym.benchmarks._machine import machine
from afvsgp_gym.evaluation import jsonable

__all__ = ["CONDITIONS", "RLBenchConfig", "evaluate_agent", "plot_curves", "run"]

ENV_ID = "afvsgp_gym/FrankaObstacleReach-v0"
#: Training conditions: name -> SafetyFilter learner (None: no filter).
CONDITIONS: dict[str, str | None] = {"afvsgp": "afvsgp", "oracle": "oracle", "unfiltered": None}
EVAL_SEED = 10_000
#: Reset seeds of the unrecorded episodes a kept filter runs before the evaluation.
WARM_SEED = 20_000
#: Runs of consecutive held-out episodes, one env and filter each, with a kept filter.
KEPT_CHUNKS = 2
SHIPPED_AGENT = Path("docs/agents/reach_ppo_afvsgp.zip")


@dataclass(frozen=True)
class RLBenchConfig:
    """Sizes of the benchmark (:meth:`quick` for the pipeline test)."""

    algo: str = "ppo"
    timesteps: int = 50_000  # agent steps: 500k env steps at the env's action repeat of 10
    seeds: tuple[int, ...] = (0, 1, 2)
    conditions: tuple[str, ...] = ("afvsgp", "oracle", "unfiltered")
    n_envs: int = 2
    eval_episodes: int = 50
    eval_workers: int = 2
    bins: int = 15
    #: unrecorded episodes a kept filter runs before the held-out goals (see evaluate_agent)
    kept_filter_warmup: int = 10
    env_kwargs: dict = field(default_factory=dict)
    algo_kwargs: dict = field(default_factory=dict)
    #: SafetyFilter options of the filtered training envs (the evaluation runs the defaults)
    filter_kwargs: dict = field(default_factory=dict)

    @classmethod
    def quick(cls) -> RLBenchConfig:
        """One seed, 512 agent steps per condition on 1.2-second episodes, 2 evaluation
        episodes: about a minute, a test of the pipeline only."""
        return cls(timesteps=512, seeds=(0,), eval_episodes=2, bins=4, kept_filter_warmup=1,
                   env_kwargs={"max_episode_steps": 300},
                   algo_kwargs={"n_steps": 128, "batch_size": 64, "n_epochs": 2})


# ------------------------------------------------------------------------------ evaluation


def _eval_episodes(task: tuple[str, str | None, list[int], dict, list[int]]) -> list[dict]:
    """Held-out episodes of the agent ``zip`` behind ``learner`` in ONE env and filter, in
    order, after the unrecorded episodes ``warm`` (the filter keeps what it learned across
    them all)."""
    import warnings

    import gymnasium as gym

    import afvsgp_gym  # noqa: F401
    from afvsgp_gym.agents.sb3 import load_policy
    from afvsgp_gym.evaluation import run_episode
    from afvsgp_gym.wrappers import SafetyFilter

    zip_path, learner, seeds, env_kwargs, warm = task
    warnings.simplefilter("ignore", RuntimeWarning)  # GP jitter notes; counted elsewhere
    env = gym.make(ENV_ID, **env_kwargs)
    if learner is not None:
        env = SafetyFilter(env, learner=learner, seed=seeds[0])
    counts: dict[str, Any] = {}

    def on_step(info: dict) -> None:
        counts["success"] = counts["success"] or bool(info["success"])
        counts["backup_steps"] += str(info.get("filter_status", "")).startswith(
            ("backup", "fallback"))

    out = []
    try:
        policy = load_policy(zip_path, env=env)
        for seed in warm:
            run_episode(env, policy, seed)
        for seed in seeds:
            counts.update(success=False, backup_steps=0)
            rec, _ = run_episode(env, policy, seed, on_step=on_step)
            rec.pop("filter_time_hist", None)
            rec.update(counts)
            out.append(rec)
    finally:
        env.close()
    return out


def _eval_episode(task: tuple[str, str | None, int, dict]) -> dict[str, Any]:
    """One held-out episode of the agent ``zip`` behind ``learner`` (fresh env and filter)."""
    zip_path, learner, seed, env_kwargs = task
    return _eval_episodes((zip_path, learner, [seed], env_kwargs, []))[0]


def evaluate_agent(zip_path: str | os.PathLike, learner: str | None, episodes: int,
                   env_kwargs: dict | None = None, pool: ProcessPoolExecutor | None = None,
                   kept_filter_warmup: int | None = None) -> dict[str, Any]:
    """Success, return and cost of the agent on ``episodes`` held-out goals (reset seeds
    ``EVAL_SEED + i``) behind ``learner`` (None: no filter).

    By default each episode runs in a fresh env and filter (the filter warms up in every
    episode, as in ``afvsgp-gym evaluate``). With ``kept_filter_warmup = n`` the filter is
    deployed as in training instead: the goals are split into :data:`KEPT_CHUNKS` runs of
    consecutive episodes, each in one env whose filter first runs ``n`` unrecorded episodes
    (reset seeds ``WARM_SEED + ...``, goals never evaluated) and keeps learning through the
    run."""
    env_kwargs = dict(env_kwargs or {})
    seeds = [EVAL_SEED + i for i in range(episodes)]
    if kept_filter_warmup is None:
        tasks = [(str(zip_path), learner, seed, env_kwargs) for seed in seeds]
        recs = list(pool.map(_eval_episode, tasks) if pool is not None
                    else map(_eval_episode, tasks))
        return _eval_summary(recs)
    n = int(kept_filter_warmup)
    if n < 0:
        raise ValueError(f"kept_filter_warmup must be >= 0 or None, got {kept_filter_warmup}")
    chunks = [c.tolist() for c in np.array_split(np.array(seeds), KEPT_CHUNKS) if c.size]
    tasks = [(str(zip_path), learner, c, env_kwargs, [WARM_SEED + j * n + i for i in range(n)])
             for j, c in enumerate(chunks)]
    runs = pool.map(_eval_episodes, tasks) if pool is not None else map(_eval_episodes, tasks)
    return _eval_summary([rec for run in runs for rec in run])


def _eval_summary(recs: list[dict]) -> dict[str, Any]:
    n = len(recs)
    succ = sum(bool(r["success"]) for r in recs)
    lo, hi = _wilson(succ, n)
    return {
        "episodes": n,
        "success_rate": succ / n,
        "success_ci95": [lo, hi],
        "return_mean": float(np.mean([r["return"] for r in recs])),
        "episodes_with_cost": int(sum(r["cost_steps"] > 0 for r in recs)),
        "cost_steps": int(sum(r["cost_steps"] for r in recs)),
        "min_h": float(min(r["min_h"] for r in recs)),
        "steps_mean": float(np.mean([r["steps"] for r in recs])),
        "interventions": int(sum(r["interventions"] for r in recs)),
        "infeasible_steps": int(sum(r["infeasible_steps"] for r in recs)),
        "backup_steps": int(sum(r["backup_steps"] for r in recs)),
    }


def _wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score 95 % interval of a binomial proportion k/n."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


# ------------------------------------------------------------------------------ curves


def _curves(episodes: list[dict], timesteps: int, bins: int) -> dict[str, list[float]]:
    """Per bin of agent steps: mean return and success rate of the episodes that ended in
    it, and the cumulative cost steps (and those after the filter's warm-up) at its end."""
    edges = np.linspace(0, timesteps, bins + 1)
    t = np.array([r["timesteps"] for r in episodes], dtype=float)
    ret = np.array([r["return"] for r in episodes], dtype=float)
    succ = np.array([r["success"] for r in episodes], dtype=float)
    cost = np.array([r["cost_steps"] for r in episodes], dtype=float)
    after = np.array([r["cost_steps_after_warmup"] for r in episodes], dtype=float)
    out: dict[str, list[float]] = {"steps": edges[1:].tolist(), "return": [], "success": [],
                                   "cumulative_cost": [], "cumulative_cost_after_warmup": []}
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (t > lo) & (t <= hi)
        out["return"].append(float(ret[inside].mean()) if inside.any() else math.nan)
        out["success"].append(float(succ[inside].mean()) if inside.any() else math.nan)
        out["cumulative_cost"].append(float(cost[t <= hi].sum()))
        out["cumulative_cost_after_warmup"].append(float(after[t <= hi].sum()))
    return out


def plot_curves(results: dict, path: str | os.PathLike) -> Path:
    """Return, success rate and cumulative training cost against agent steps (mean over
    seeds, band min..max), one line per condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"afvsgp": "tab:blue", "oracle": "tab:green", "unfiltered": "tab:red"}
    labels = {"afvsgp": "AFVSGP filter (nominal zero)", "oracle": "oracle filter",
              "unfiltered": "no filter"}
    panels = (("return", "episode return"), ("success", "success rate"),
              ("cumulative_cost", "cumulative cost steps"))
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for cond in results["config"]["conditions"]:
        runs = [r for r in results["runs"] if r["condition"] == cond]
        if not runs:
            continue
        x = np.array(runs[0]["curves"]["steps"]) / 1e3
        for ax, (key, _) in zip(axes, panels, strict=True):
            y = np.array([r["curves"][key] for r in runs], dtype=float)
            with np.errstate(all="ignore"):
                mean = np.nanmean(y, axis=0) if np.isfinite(y).any() else y[0]
            ax.plot(x, mean, color=colors.get(cond), label=labels.get(cond, cond))
            if len(runs) > 1:
                ax.fill_between(x, np.nanmin(y, axis=0), np.nanmax(y, axis=0),
                                color=colors.get(cond), alpha=0.2, linewidth=0)
    for ax, (_, title) in zip(axes, panels, strict=True):
        ax.set_xlabel("agent steps (x 1000; 10 env steps each)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[1].set_ylim(-0.02, 1.02)
    axes[2].set_yscale("symlog", linthresh=10)
    axes[2].set_ylim(bottom=0)
    axes[0].legend(loc="lower right", fontsize=8)
    n = len(results["config"]["seeds"])
    fig.suptitle(f"{results['config']['algo'].upper()} on FrankaObstacleReach-v0, {n} seed(s): "
                 "mean, band = min..max over seeds", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------ table


def _fmt_rate(s: dict) -> str:
    lo, hi = s["success_ci95"]
    return f"{100 * s['success_rate']:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


def table_markdown(results: dict) -> str:
    """Per-condition rows (seeds pooled for the evaluation, summed for training cost)."""
    head = ("| condition | held-out success, own condition (95 % CI) | held-out success behind "
            "AFVSGP | behind a kept AFVSGP filter | eval. episodes with cost | eval. return | "
            "training cost steps (after warm-up) | training episodes with cost | final training "
            "success | wall time per run |\n|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for cond in results["config"]["conditions"]:
        runs = [r for r in results["runs"] if r["condition"] == cond]
        if not runs:
            continue
        own = _pool([r["eval_own"] for r in runs])
        afv = _pool([r["eval_afvsgp"] for r in runs])
        kept = _pool([r["eval_afvsgp_kept"] for r in runs])
        cost = sum(r["training"]["cost_steps"] for r in runs)
        after = sum(r["training"]["cost_steps_after_warmup"] for r in runs)
        eps_cost = sum(r["training"]["episodes_with_cost"] for r in runs)
        eps = sum(r["training"]["episodes"] for r in runs)
        final = np.mean([r["training"]["final_success"] for r in runs])
        wall = np.mean([r["train_wall_s"] for r in runs])
        lines.append(
            f"| {cond} | {_fmt_rate(own)} | {_fmt_rate(afv)} | {_fmt_rate(kept)} | "
            f"{own['episodes_with_cost'] + kept['episodes_with_cost']} of "
            f"{own['episodes'] + kept['episodes']} | {own['return_mean']:.2f} | {cost} ({after}) | "
            f"{eps_cost} of "
            f"{eps} | {100 * final:.0f} % | {wall / 60:.1f} min |")
    per_seed = ["", "| condition | seed | success own | success behind AFVSGP | behind a kept "
                "AFVSGP filter | eval. cost episodes | training cost steps | final training "
                "success |", "|---|---|---|---|---|---|---|---|"]
    for r in results["runs"]:
        per_seed.append(
            f"| {r['condition']} | {r['seed']} | {100 * r['eval_own']['success_rate']:.0f} % | "
            f"{100 * r['eval_afvsgp']['success_rate']:.0f} % | "
            f"{100 * r['eval_afvsgp_kept']['success_rate']:.0f} % | "
            f"{r['eval_own']['episodes_with_cost'] + r['eval_afvsgp_kept']['episodes_with_cost']}"
            f" | {r['training']['cost_steps']} | "
            f"{100 * r['training']['final_success']:.0f} % |")
    return "\n".join(lines + per_seed) + "\n"


def _pool(summaries: Sequence[dict]) -> dict[str, Any]:
    """Pool evaluation summaries of several seeds (episode-weighted)."""
    n = sum(s["episodes"] for s in summaries)
    k = round(sum(s["success_rate"] * s["episodes"] for s in summaries))
    return {
        "episodes": n,
        "success_rate": k / n,
        "success_ci95": list(_wilson(k, n)),
        "return_mean": sum(s["return_mean"] * s["episodes"] for s in summaries) / n,
        "episodes_with_cost": sum(s["episodes_with_cost"] for s in summaries),
    }


# ------------------------------------------------------------------------------ run


def _training_summary(episodes: list[dict]) -> dict[str, Any]:
    last = episodes[-max(1, len(episodes) // 10):] if episodes else []
    return {
        "episodes": len(episodes),
        "cost_steps": int(sum(r["cost_steps"] for r in episodes)),
        "cost_steps_after_warmup": int(sum(r["cost_steps_after_warmup"] for r in episodes)),
        "episodes_with_cost": int(sum(r["cost_steps"] > 0 for r in episodes)),
        "warmup_steps": int(sum(r["warmup_steps"] for r in episodes)),
        "final_success": float(np.mean([r["success"] for r in last])) if last else math.nan,
        "final_return": float(np.mean([r["return"] for r in last])) if last else math.nan,
        "interventions": int(sum(r["interventions"] for r in episodes)),
        "infeasible_steps": int(sum(r["infeasible_steps"] for r in episodes)),
        "backup_steps": int(sum(r["backup_steps"] for r in episodes)),
        "saturated_steps": int(sum(r["saturated_steps"] for r in episodes)),
    }


def run(cfg: RLBenchConfig, out_dir: str | os.PathLike, *, figure: str | os.PathLike | None
        = None, ship: str | os.PathLike | None = None,
        log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train and evaluate every (condition, seed); write results, table, figure (and the
    shipped agent when ``ship`` is set). Returns the results dict."""
    from afvsgp_gym.agents.sb3 import train
    from afvsgp_gym.executors import one_blas_thread

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    unknown = set(cfg.conditions) - set(CONDITIONS)
    if unknown:
        raise ValueError(f"unknown condition(s) {sorted(unknown)}; valid: {list(CONDITIONS)}")
    t_start = time.perf_counter()
    env_kwargs = dict(cfg.env_kwargs)
    results: dict[str, Any] = {"config": asdict(cfg), "machine": machine(), "runs": []}
    ctx = get_context("forkserver")
    for seed in cfg.seeds:  # every condition of a seed before the next seed
        for cond in cfg.conditions:
            name = f"{cfg.algo}_{cond}_s{seed}"
            log(f"[rl] training {name} ({cfg.timesteps} agent steps)")
            res = train(cfg.algo, ENV_ID, learner=CONDITIONS[cond], timesteps=cfg.timesteps,
                        path=out_dir / f"{name}.zip", seed=seed, n_envs=cfg.n_envs,
                        env_kwargs=env_kwargs, algo_kwargs=dict(cfg.algo_kwargs),
                        filter_kwargs=dict(cfg.filter_kwargs) if CONDITIONS[cond] else None,
                        log_dir=out_dir / name)
            tsum = _training_summary(res.episodes)
            log(f"[rl]   {res.wall_time_s:.0f} s, {tsum['episodes']} episodes, cost steps "
                f"{tsum['cost_steps']} ({tsum['cost_steps_after_warmup']} after warm-up), final "
                f"training success {tsum['final_success']:.2f}")
            t_eval = time.perf_counter()
            with one_blas_thread(), ProcessPoolExecutor(cfg.eval_workers, mp_context=ctx) as pool:
                own = evaluate_agent(res.path, CONDITIONS[cond], cfg.eval_episodes, env_kwargs,
                                     pool)
                behind = own if cond == "afvsgp" else evaluate_agent(
                    res.path, "afvsgp", cfg.eval_episodes, env_kwargs, pool)
                kept = evaluate_agent(res.path, "afvsgp", cfg.eval_episodes, env_kwargs, pool,
                                      kept_filter_warmup=cfg.kept_filter_warmup)
            log(f"[rl]   held-out success {own['success_rate']:.2f} ({cond}), "
                f"{behind['success_rate']:.2f} behind AFVSGP, {kept['success_rate']:.2f} behind "
                f"a kept AFVSGP filter; episodes with cost {own['episodes_with_cost']} / "
                f"{behind['episodes_with_cost']} / {kept['episodes_with_cost']}")
            results["runs"].append({
                "condition": cond, "seed": seed, "zip": str(res.path),
                "train_wall_s": res.wall_time_s, "eval_wall_s": time.perf_counter() - t_eval,
                "timesteps": res.timesteps, "env_steps": res.env_steps,
                "training": tsum, "curves": _curves(res.episodes, cfg.timesteps, cfg.bins),
                "eval_own": own, "eval_afvsgp": behind, "eval_afvsgp_kept": kept,
            })
    results["total_wall_s"] = time.perf_counter() - t_start
    (out_dir / "rl_results.json").write_text(json.dumps(jsonable(results), indent=1) + "\n")
    table = table_markdown(results)
    (out_dir / "rl_table.md").write_text(table)
    fig = plot_curves(results, figure or out_dir / "rl_training.png")
    log(table)
    log(f"[rl] figure {fig}; total wall time {results['total_wall_s'] / 60:.1f} min on "
        f"{results['machine']}")
    if ship is not None:
        best = _best_filtered(results)
        if best is not None:
            Path(ship).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(best["zip"], ship)
            log(f"[rl] shipped {best['zip']} (seed {best['seed']}) as {ship}")
    return results


def _best_filtered(results: dict) -> dict | None:
    runs = [r for r in results["runs"] if r["condition"] == "afvsgp"]
    if not runs:
        return None
    return max(runs, key=lambda r: (-r["eval_own"]["episodes_with_cost"],
                                    r["eval_own"]["success_rate"], r["eval_own"]["return_mean"]))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/rl_benchmark.py",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="the pipeline in minutes")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="runs, logs, results (default benchmarks/rl_runs, rl_quick with --quick)")
    p.add_argument("--timesteps", type=int, default=None, help="agent steps per run")
    p.add_argument("--seeds", default=None, metavar="0,1,2")
    p.add_argument("--conditions", default=None, metavar="afvsgp,oracle,unfiltered")
    p.add_argument("--filter-kwargs", default=None, metavar="JSON",
                   help="SafetyFilter options of the filtered training envs, e.g. "
                   "'{\"online_exploration\": 0.05}' (the evaluation runs the defaults)")
    p.add_argument("--figure", default=None, metavar="PNG",
                   help="training curves (default docs/rl_training.png; with --quick, in --out)")
    p.add_argument("--no-ship", action="store_true", help="do not copy the best agent to docs/")
    args = p.parse_args(argv)
    cfg = RLBenchConfig.quick() if args.quick else RLBenchConfig()
    if args.timesteps is not None:
        cfg = replace(cfg, timesteps=int(args.timesteps))
    if args.seeds:
        cfg = replace(cfg, seeds=tuple(int(s) for s in args.seeds.split(",")))
    if args.conditions:
        cfg = replace(cfg, conditions=tuple(s.strip() for s in args.conditions.split(",")))
    if args.filter_kwargs:
        from afvsgp_gym.cli import json_object_arg
        from afvsgp_gym.sweep.validate import filter_kwarg_names

        kwargs = json_object_arg(p, args.filter_kwargs, "--filter-kwargs")
        unknown = sorted(set(kwargs) - set(filter_kwarg_names()))
        if unknown:
            p.error(f"--filter-kwargs: unknown SafetyFilter option(s) {unknown}")
        cfg = replace(cfg, filter_kwargs=kwargs)
    out = Path(args.out or ("rl_quick" if args.quick else "benchmarks/rl_runs"))
    full = not args.quick
    figure = args.figure or (Path("docs/rl_training.png") if full else None)
    run(cfg, out, figure=figure,
        ship=SHIPPED_AGENT if full and not args.no_ship else None,
        log=lambda m: print(m, file=sys.stderr, flush=True))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
