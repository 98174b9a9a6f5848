"""``afvsgp-gym`` console script: evaluate, sweep, report, reproduce, plot, video, train, bench,
robot.

Each subcommand validates its arguments (unknown env ids, agents and learners list the valid
choices and exit with status 2; the values of ``--env-kwargs`` and ``--filter-kwargs`` are
checked by building the env and the filter once, and output paths for writability, before any
work starts) and then calls one library function:

- ``evaluate``  -> :func:`afvsgp_gym.evaluation.evaluate`
- ``sweep``     -> :func:`afvsgp_gym.sweep.run_sweep` (after :func:`afvsgp_gym.sweep.validate`)
- ``report``    -> :func:`afvsgp_gym.sweep.report`
- ``reproduce`` -> :func:`afvsgp_gym.reproduce.reproduce`
- ``plot``      -> :func:`afvsgp_gym.reproduce.render_figures`
- ``video``     -> :func:`afvsgp_gym.video.record_video`
- ``train``     -> :func:`afvsgp_gym.agents.sb3.train`
- ``bench``     -> :func:`afvsgp_gym.benchmarks.run_all.run_all`
- ``robot``     -> :func:`afvsgp_gym.robots.run.run_simulated` (``--simulate``) or
  :func:`afvsgp_gym.robots.run.run_robot` (``--host``)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["build_parser", "main"]

DEFAULT_ENV = "afvsgp_gym/FrankaObstacleDynamic-v0"
#: The SCHED_FIFO priority of ``robot``'s loop unless told otherwise (0: normal priority).
ROBOT_RT_PRIORITY = 50
TRAIN_ENV = "afvsgp_gym/FrankaObstacleReach-v0"


# ----------------------------------------------------------------------------- choices


def env_ids() -> list[str]:
    """Registered ``afvsgp_gym/...`` ids."""
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401

    return sorted(k for k in gym.registry if k.startswith("afvsgp_gym/"))


def learner_names() -> tuple[str, ...]:
    """``"auto"`` (the env's suggestion, ``SafetyFilter``'s default) and the learners."""
    from afvsgp_gym.cbf import LEARNERS
    from afvsgp_gym.wrappers.safety_filter import AUTO_LEARNER

    return (AUTO_LEARNER, *LEARNERS)


def _check_env(parser: argparse.ArgumentParser, env_id: str) -> str:
    ids = env_ids()
    if env_id not in ids:
        parser.error(f"unknown env id {env_id!r}; valid choices: {', '.join(ids)}")
    return env_id


def _check_learner(parser: argparse.ArgumentParser, name: str, opt: str = "--learner") -> str:
    valid = learner_names()
    if name not in valid:
        parser.error(f"unknown learner {name!r} for {opt}; valid choices: {', '.join(valid)}")
    return name


def _check_agent(parser: argparse.ArgumentParser, agent: str) -> str:
    from afvsgp_gym.evaluation import BUILTIN_AGENTS

    if agent in BUILTIN_AGENTS:
        return agent
    if agent.endswith(".zip"):
        if not Path(agent).is_file():
            parser.error(f"agent zip {agent!r} does not exist")
        _require_sb3(parser)
        return agent
    parser.error(f"unknown agent {agent!r}; valid choices: {', '.join(BUILTIN_AGENTS)} or a "
                 "path to a Stable-Baselines3 .zip saved by 'afvsgp-gym train'")
    raise AssertionError  # unreachable: parser.error exits


def _check_agent_fits(parser: argparse.ArgumentParser, agent: str, env_id: str,
                      env_kwargs: dict) -> None:
    """A model zip must match the env's spaces; checked before the run starts."""
    if not agent.endswith(".zip"):
        return
    import gymnasium as gym

    from afvsgp_gym.agents.sb3 import load_policy

    env = gym.make(env_id, **env_kwargs)
    try:
        load_policy(agent, env=env)
    except ValueError as exc:
        parser.error(str(exc))
    finally:
        env.close()


def _check_kwargs(parser: argparse.ArgumentParser, env_id: str, learners: Sequence[str | None],
                  env_kwargs: dict, filter_kwargs: dict) -> None:
    """The env and each learner's filter built once with the given kwargs before the run, so
    that a bad value is an argument error naming its option, not a traceback of the run."""
    import gymnasium as gym

    from afvsgp_gym.wrappers import SafetyFilter

    try:
        env = gym.make(env_id, **env_kwargs)
    except Exception as exc:
        parser.error(f"--env-kwargs: {type(exc).__name__}: {exc}")
    try:
        for learner in learners:
            if learner is not None:
                SafetyFilter(env, learner=learner, **filter_kwargs)
    except Exception as exc:
        parser.error(f"--filter-kwargs: {type(exc).__name__}: {exc}")
    finally:
        env.close()


def _require_sb3(parser: argparse.ArgumentParser) -> None:
    from afvsgp_gym.agents.sb3 import require_sb3

    try:
        require_sb3()
    except ImportError as exc:
        parser.exit(3, f"{parser.prog}: error: {exc}\n")


def _check_out(parser: argparse.ArgumentParser, path: str | None, opt: str,
               directory: bool = False) -> Path | None:
    if path is None:
        return None
    from afvsgp_gym.evaluation import check_writable

    try:
        return check_writable(path, directory=directory)
    except ValueError as exc:
        parser.error(f"{opt}: {exc}")
    raise AssertionError  # unreachable


def json_object_arg(parser: argparse.ArgumentParser, text: str | None, opt: str) -> dict:
    """The JSON object given to option ``opt`` ({} when absent), or ``parser.error`` naming it."""
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        parser.error(f"{opt} must be a JSON object: {exc}")
    if not isinstance(value, dict):
        parser.error(f"{opt} must be a JSON object, got {type(value).__name__}")
    return value


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def _require_ray(parser: argparse.ArgumentParser) -> None:
    from afvsgp_gym.executors import require_ray

    try:
        require_ray()
    except ImportError as exc:
        parser.exit(3, f"{parser.prog}: error: {exc}\n")


def _executor(parser: argparse.ArgumentParser, workers: int | None, ray: str | None,
              inline_single: bool) -> Any:
    from afvsgp_gym.executors import make_executor

    if ray:
        _require_ray(parser)
    return make_executor(workers, ray, inline_single=inline_single)


# ----------------------------------------------------------------------------- subcommands


def _cmd_evaluate(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.evaluation import evaluate, format_table, write_csv, write_json

    _check_env(parser, args.env)
    if args.compare:
        from afvsgp_gym.evaluation import UNFILTERED

        learners = [s.strip() for s in args.compare.split(",") if s.strip()]
        if not learners:
            parser.error("--compare needs a comma-separated list of learners")
        for name in learners:
            if name != UNFILTERED:
                _check_learner(parser, name, "--compare")
        learners = [None if name == UNFILTERED else name for name in learners]
    else:
        learners = [_check_learner(parser, args.learner)]
    _check_agent(parser, args.agent)
    json_path = _check_out(parser, args.json, "--json")
    csv_path = _check_out(parser, args.csv, "--csv")
    env_kwargs = json_object_arg(parser, args.env_kwargs, "--env-kwargs")
    _check_agent_fits(parser, args.agent, args.env, env_kwargs)
    filter_kwargs = json_object_arg(parser, args.filter_kwargs, "--filter-kwargs")
    _check_kwargs(parser, args.env, learners, env_kwargs, filter_kwargs)
    with _executor(parser, args.workers, args.ray, inline_single=True) as executor:
        result = evaluate(args.env, agent=args.agent, learners=learners,
                          episodes=args.episodes, seed=args.seed, max_steps=args.max_steps,
                          env_kwargs=env_kwargs, filter_kwargs=filter_kwargs,
                          progress=not args.no_progress, executor=executor)
    print(f"env {args.env}, agent {args.agent}, seeds {args.seed}..{args.seed + args.episodes - 1}"
          f" (filter times in microseconds)")
    print(format_table(result))
    if json_path is not None:
        write_json(result, json_path)
        print(f"wrote {json_path}")
    if csv_path is not None:
        write_csv(result, csv_path)
        print(f"wrote {csv_path}")
    return 0


def _cmd_sweep(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.sweep import ConfigError, load_config, run_sweep, validate

    if args.ray:
        _require_ray(parser)
    out = args.out or str(Path(args.config).with_suffix(".results.jsonl").name)
    out_path = _check_out(parser, out, "--out")
    json_path = _check_out(parser, args.json, "--json")
    png_path = _check_out(parser, args.png, "--png")
    try:
        sweep = load_config(args.config)
        episodes = sweep.episodes()
        print(f"{args.config}: {len(episodes)} episodes in {len(sweep.blocks)} grid(s)"
              + (f" ({sweep.size() - len(episodes)} repeated across grids, run once)"
                 if sweep.size() > len(episodes) else ""), flush=True)
        validate(sweep)
    except ConfigError as exc:
        parser.error(str(exc))
    if args.dry_run:
        for block in sweep.blocks:
            print(f"  {block.name}: {len(block.specs())} episodes")
        print("configuration valid; nothing run (--dry-run)")
        return 0
    executor = _executor(parser, args.workers, args.ray, inline_single=False)
    print(f"results -> {out_path} ({executor.workers} worker(s), "
          f"{type(executor).__name__})", flush=True)
    try:
        with executor:
            res = run_sweep(episodes, out_path, executor, progress=not args.no_progress,
                            limit=args.limit)
    except KeyboardInterrupt:
        print(f"interrupted; finished episodes are in {out_path}: re-run the same command to "
              "resume", file=sys.stderr)
        return 130
    except RuntimeError as exc:
        parser.exit(1, f"{parser.prog}: error: {exc}\n")
    left = len(episodes) - res.skipped - res.ran - len(res.failed)
    print(f"{res.ran} episodes run, {res.skipped} already finished, {len(res.failed)} failed"
          + (f", {left} left for the next run" if left else ""))
    if res.records:
        _print_report(parser, res.records, None, json_path, png_path)
    if res.failed:
        print(f"{len(res.failed)} episode(s) failed (tracebacks above); re-run to retry them",
              file=sys.stderr)
        return 1
    return 0


def _print_report(parser: argparse.ArgumentParser, records: list, by: list | None,
                  json_path: Path | None, png_path: Path | None, confidence: float = 0.95,
                  markdown: bool = False) -> None:
    from afvsgp_gym.sweep.plot import plot_report
    from afvsgp_gym.sweep.report import format_report, report, write_report_json

    try:
        rep, groups = report(records, by, confidence)
    except ValueError as exc:
        parser.error(str(exc))
    print(format_report(rep, markdown=markdown))
    if json_path is not None:
        print(f"wrote {write_report_json(rep, json_path)}")
    if png_path is not None:
        print(f"wrote {plot_report(rep, groups, png_path)}")


def _cmd_report(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.sweep.results import read_records

    json_path = _check_out(parser, args.json, "--json")
    png_path = _check_out(parser, args.png, "--png")
    if not 0.0 < args.confidence < 1.0:
        parser.error(f"--confidence must be in (0, 1), got {args.confidence}")
    try:
        records = read_records(args.results)
    except ValueError as exc:
        parser.error(str(exc))
    if not records:
        parser.error(f"{args.results} holds no finished episode")
    by = [s.strip() for s in args.by.split(",") if s.strip()] if args.by else None
    _print_report(parser, records, by, json_path, png_path, args.confidence, args.markdown)
    return 0


def _cmd_reproduce(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.reproduce import ReproduceConfig, reproduce, table1_markdown

    out = args.out or ("reproduce_quick" if args.quick else "docs")  # quick never overwrites docs
    out_dir = _check_out(parser, out, "--out", directory=True)
    json_path = _check_out(parser, args.json, "--json")
    cfg = ReproduceConfig.quick() if args.quick else ReproduceConfig()
    if args.seed is not None:
        from dataclasses import replace

        cfg = replace(cfg, seed=args.seed)

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    result = reproduce(cfg, out_dir=out_dir, json_path=json_path, log=log)
    print(table1_markdown(result))
    if out_dir is not None:
        print(f"figures, tables and traces in {out_dir}")
    if json_path is not None or out_dir is not None:
        print(f"wrote {json_path or out_dir / 'reproduce.json'}")
    return 0


def _cmd_plot(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.reproduce import render_figures

    traces = Path(args.traces)
    if traces.is_dir():
        traces = traces / "traces.npz"
    if not traces.is_file():
        parser.error(f"no traces file at {str(traces)!r}; run 'afvsgp-gym reproduce --out DIR' "
                     "first (it writes DIR/traces.npz)")
    out_dir = _check_out(parser, args.out or str(traces.parent), "--out", directory=True)
    for p in render_figures(traces, out_dir):
        print(f"wrote {p}")
    return 0


def _cmd_video(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.video import VIDEO_SUFFIXES, record_video

    _check_env(parser, args.env)
    _check_learner(parser, args.learner)
    _check_agent(parser, args.agent)
    if Path(args.out).suffix.lower() not in VIDEO_SUFFIXES:
        parser.error(f"--out must end in one of {', '.join(VIDEO_SUFFIXES)}, got {args.out!r}")
    out = _check_out(parser, args.out, "--out")
    env_kwargs = json_object_arg(parser, args.env_kwargs, "--env-kwargs")
    _check_kwargs(parser, args.env, [args.learner], env_kwargs, {})
    os.environ.setdefault("MUJOCO_GL", "egl")
    res = record_video(args.env, out, agent=args.agent, learner=args.learner, seed=args.seed,
                       max_steps=args.max_steps, every=args.every, env_kwargs=env_kwargs)
    print(f"wrote {res['path']}: {res['frames']} frames of {res['steps']} steps, "
          f"min h = {res['min_h']:.4f}, {res['violation_steps']} steps with h < 0")
    return 0


def _cmd_train(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    _check_env(parser, args.env)
    learner = None if args.no_filter else _check_learner(parser, args.learner)
    _require_sb3(parser)
    from afvsgp_gym.agents.sb3 import train

    tag = "unfiltered" if learner is None else learner
    out = args.out or f"{args.algo}_{args.env.split('/')[-1]}_{tag}.zip"
    if not out.endswith(".zip"):
        parser.error(f"--out must end in .zip, got {out!r}")
    out_path = _check_out(parser, out, "--out")
    log_dir = _check_out(parser, args.log_dir, "--log-dir", directory=True)
    env_kwargs = json_object_arg(parser, args.env_kwargs, "--env-kwargs")
    filter_kwargs = json_object_arg(parser, args.filter_kwargs, "--filter-kwargs")
    _check_kwargs(parser, args.env, [learner], env_kwargs, filter_kwargs)
    res = train(args.algo, args.env, learner=learner, timesteps=args.timesteps,
                path=out_path, seed=args.seed, n_envs=args.n_envs,
                action_repeat=args.action_repeat, env_kwargs=env_kwargs,
                filter_kwargs=filter_kwargs,
                algo_kwargs=json_object_arg(parser, args.algo_kwargs, "--algo-kwargs"),
                log_dir=log_dir, verbose=args.verbose)
    behind = "no filter" if learner is None else f"SafetyFilter(learner={learner!r})"
    print(f"trained {args.algo.upper()} for {res.timesteps} agent steps ({res.env_steps} env "
          f"steps) on {args.env} behind {behind} in {res.wall_time_s:.0f} s")
    eps = res.episodes
    if eps:
        last = eps[-max(1, len(eps) // 10):]
        cost = sum(r["cost_steps"] for r in eps)
        after = sum(r["cost_steps_after_warmup"] for r in eps)
        print(f"episodes: {len(eps)}; cost steps (h < 0, contact or limits): {cost} in total, "
              f"{after} after the filter's warm-up; last {len(last)} episodes: success "
              f"{sum(r['success'] for r in last) / len(last):.0%}, return "
              f"{sum(r['return'] for r in last) / len(last):.2f}")
    else:
        print("no training episode finished (increase --timesteps to see episode statistics)")
    if log_dir is not None:
        print(f"logs in {log_dir} (episodes.csv, progress.csv)")
    print(f"saved {res.path}; evaluate (behind the filter) with: afvsgp-gym evaluate --env "
          f"{args.env} --agent {res.path} --learner {learner or 'afvsgp'}")
    return 0


def _cmd_bench(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.benchmarks.run_all import AREAS, run_all

    only = None
    if args.only:
        only = [s.strip() for s in args.only.split(",") if s.strip()]
        bad = [a for a in only if a not in AREAS]
        if bad:
            parser.error(f"unknown benchmark area(s) {bad}; valid choices: {', '.join(AREAS)}")
    results = run_all(quick=args.quick, areas=only)
    return 0 if any(v is not None for v in results.values()) else 1


def _floats(parser: argparse.ArgumentParser, text: str, opt: str, n: int) -> list[float]:
    """``n`` comma-separated finite numbers (one is repeated ``n`` times), or an error naming
    ``opt``."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        parser.error(f"{opt} must be comma-separated numbers, got {text!r}")
    if len(values) == 1:
        values = values * n
    if len(values) != n or not all(v == v and abs(v) != float("inf") for v in values):
        parser.error(f"{opt} must be 1 or {n} finite numbers, got {text!r}")
    return values


def _robot_obstacles(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list:
    """The ``--obstacles`` (the envs' dicts) and ``--obstacle`` (fixed spheres) of ``robot`` as
    ObstacleSpecs, in that order, or ``parser.error`` naming the option and the entry."""
    from afvsgp_gym.robots.run import obstacle_specs

    typed = []
    if args.obstacles:
        try:
            typed = json.loads(args.obstacles)
        except json.JSONDecodeError as exc:
            parser.error(f"--obstacles must be a JSON list of objects: {exc}")
        if not isinstance(typed, list) or not all(isinstance(o, dict) for o in typed):
            parser.error("--obstacles must be a JSON list of objects (the envs' obstacles=), "
                         f"got {args.obstacles!r}")
    spheres = [_floats(parser, o, "--obstacle", 4) for o in args.obstacle or []]
    if any(o[3] <= 0 for o in spheres):
        parser.error("--obstacle radius must be > 0")
    try:
        specs = obstacle_specs(typed)
    except ValueError as exc:
        parser.error(f"--obstacles: {exc}")
    return specs + obstacle_specs(spheres)


def _cmd_robot(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from afvsgp_gym.robots.policies import ROBOT_AGENTS

    if args.simulate == (args.host is not None):
        parser.error("give exactly one of --simulate and --host IP")
    if not args.seconds > 0:
        parser.error(f"--seconds must be > 0, got {args.seconds}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if not 0 < args.budget < 1.0:
        parser.error(f"--budget must be in (0, 1) ms, got {args.budget}")
    agent = args.agent or ("nominal" if args.simulate else "hold")
    if agent not in ROBOT_AGENTS:
        parser.error(f"unknown agent {agent!r} for --agent; valid choices: "
                     f"{', '.join(ROBOT_AGENTS)} (the subset of evaluate's agents that needs "
                     "no simulation: docs/robot.md)")
    _check_learner(parser, args.learner)
    from afvsgp_gym.cbf.learners import REGISTRY

    if REGISTRY[args.learner].true_terms:
        parser.error(f"--learner {args.learner} needs the true terms, which a robot does not "
                     "have")
    torque_error = _floats(parser, args.torque_error, "--torque-error", 7)
    if any(v < 0 for v in torque_error):
        parser.error(f"--torque-error must be >= 0, got {args.torque_error!r}")
    obstacles = _robot_obstacles(parser, args)
    if args.payload < 0:
        parser.error(f"--payload must be >= 0, got {args.payload}")
    if not args.obstacle_noise >= 0:
        parser.error(f"--obstacle-noise must be >= 0, got {args.obstacle_noise}")
    if args.host is not None and args.obstacle_noise:
        parser.error("--obstacle-noise is for --simulate (a robot's obstacles are its own)")
    if not 0 <= args.rt_priority <= 99:
        parser.error(f"--rt-priority must be in 0..99 (0: normal priority), got "
                     f"{args.rt_priority}")
    filter_kwargs = json_object_arg(parser, args.filter_kwargs, "--filter-kwargs")
    json_path = _check_out(parser, args.json, "--json")
    from afvsgp_gym.robots import libfranka
    from afvsgp_gym.robots.run import realtime_priority, run_robot, run_simulated

    if args.host is not None:
        try:
            import pylibfranka  # noqa: F401
        except ImportError:
            parser.exit(3, f"{parser.prog}: error: --host needs pylibfranka, the optional "
                           f"extra 'robot': {libfranka.INSTALL_HINT}\n")
    budget = args.budget * 1e-3
    with contextlib.ExitStack() as stack:
        try:  # a robot's loop refuses to start without it, as libfranka's does
            scheduler = stack.enter_context(
                realtime_priority(args.rt_priority, enforce=args.host is not None))
            if args.rt_priority and not scheduler.startswith("SCHED_FIFO"):
                print(f"{parser.prog}: note: running at normal priority: {scheduler}",
                      file=sys.stderr)
            if args.simulate:
                report = run_simulated(args.seconds, agent=agent, learner=args.learner,
                                       budget=budget, torque_error=torque_error,
                                       robot_kwargs={"payload_mass": args.payload,
                                                     "obstacle_noise": args.obstacle_noise,
                                                     "obstacles": obstacles or None},
                                       filter_kwargs=filter_kwargs,
                                       self_collision=args.self_collision, seed=args.seed)
            else:
                report = run_robot(args.host, args.seconds, obstacles=obstacles, agent=agent,
                                   learner=args.learner, budget=budget,
                                   torque_error=torque_error, filter_kwargs=filter_kwargs,
                                   self_collision=args.self_collision, seed=args.seed)
        except (RuntimeError, OSError) as exc:  # no priority, no connection, a state that
            print(f"{parser.prog}: error: {exc}", file=sys.stderr)  # stops the start
            return 1
    out = report.to_dict()
    from afvsgp_gym.benchmarks._machine import machine

    out.update(mode="simulate" if args.simulate else "host", agent=agent, learner=args.learner,
               budget_ms=args.budget, torque_error_nm=torque_error, scheduler=scheduler,
               machine=machine(), load_average=list(os.getloadavg()))
    st = report.step_time_ms
    print(f"{report.steps} steps in {report.seconds:.2f} s ({report.rate_hz:.1f} Hz), "
          f"{report.deadline_misses} deadline misses (budget {args.budget:g} ms), "
          f"{report.cost_steps} steps with cost ({report.cost_source}), stop: "
          f"{report.stop_reason}")
    if st:
        print("step time (ms): " + ", ".join(f"{k} {v:.3f}" for k, v in st.items()))
    if json_path is not None:
        json_path.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {json_path}")
    return 0 if report.stop_reason == "completed" else 1


# ----------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree (choices that need imports are checked after parsing)."""
    p = argparse.ArgumentParser(
        prog="afvsgp-gym",
        description="Learned HOCBF safety filter (AFVSGP + chance-constrained SOCP) on Franka "
                    "obstacle-avoidance environments.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    ev = sub.add_parser("evaluate", help="seeded episodes behind the safety filter, safety report",
                        description="Run seeded episodes of an agent behind the safety filter "
                                    "and print a per-episode safety report and a summary.")
    ev.add_argument("--env", default=DEFAULT_ENV, help=f"env id (default {DEFAULT_ENV})")
    ev.add_argument("--agent", default="nominal",
                    help="nominal | random | ram | swing1..swing7 | greedy | untrained-ppo "
                         "(policies built to break the filter) | PATH.zip (Stable-Baselines3; "
                         "default nominal)")
    ev.add_argument("--learner", default="auto",
                    help="filter learner (default auto: the env's suggestion, as SafetyFilter)")
    ev.add_argument("--compare", default=None, metavar="A,B,...",
                    help="several learners side by side on the same seeds (overrides --learner); "
                         "'unfiltered' runs the env without a filter")
    ev.add_argument("--episodes", type=_positive, default=3)
    ev.add_argument("--seed", type=int, default=0, help="episode i uses seed + i")
    ev.add_argument("--max-steps", type=_positive, default=None,
                    help="cap the steps per episode (default: the env's time limit)")
    ev.add_argument("--json", default=None, metavar="PATH")
    ev.add_argument("--csv", default=None, metavar="PATH")
    ev.add_argument("--env-kwargs", default=None, metavar="JSON",
                    help='extra gym.make kwargs, e.g. \'{"nominal_model": "kinematic"}\'')
    ev.add_argument("--filter-kwargs", default=None, metavar="JSON",
                    help='SafetyFilter options, e.g. \'{"beta": 1.0}\'')
    ev.add_argument("--no-progress", action="store_true", help="no progress bar")
    ev.add_argument("--workers", type=_positive, default=1,
                    help="episodes in parallel worker processes (default 1: this process)")
    ev.add_argument("--ray", default=None, metavar="ADDRESS",
                    help="run the episodes as Ray tasks: auto, local or a cluster address "
                         "(extra 'cluster')")

    sw = sub.add_parser("sweep", help="a seeded grid of episodes in parallel, resumable",
                        description="Run every episode of CONFIG (TOML, JSON or YAML: grids of "
                                    "envs x env kwargs x learners x filter kwargs x agents x "
                                    "seeds) on a local process pool or Ray, appending one JSON "
                                    "line per finished episode to --out; re-running the same "
                                    "command skips finished episodes. See "
                                    "afvsgp_gym/sweep/config.py for the format.")
    sw.add_argument("config", metavar="CONFIG")
    sw.add_argument("--out", default=None, metavar="RESULTS.jsonl",
                    help="results file (default CONFIG_NAME.results.jsonl here)")
    sw.add_argument("--workers", type=_positive, default=None,
                    help="worker processes (default: every core), or CPUs with --ray local")
    sw.add_argument("--ray", default=None, metavar="ADDRESS",
                    help="run on Ray: auto (this machine's cluster), local (a private "
                         "instance) or an address (extra 'cluster')")
    sw.add_argument("--dry-run", action="store_true", help="check CONFIG and count, run nothing")
    sw.add_argument("--limit", type=_positive, default=None, metavar="N",
                    help="run at most N of the unfinished episodes (a slice; re-run to go on)")
    sw.add_argument("--json", default=None, metavar="PATH", help="report as JSON")
    sw.add_argument("--png", default=None, metavar="PATH", help="report as a PNG plot")
    sw.add_argument("--no-progress", action="store_true", help="no progress bar")

    rr = sub.add_parser("report", help="per-configuration safety report of sweep results",
                        description="Per configuration: episodes, episodes with cost and the "
                                    "exact Clopper-Pearson upper bound on the per-episode cost "
                                    "rate, min h, contacts, tracking error, backup steps, "
                                    "filter time median and p99.")
    rr.add_argument("results", metavar="RESULTS", help="a results file written by sweep")
    rr.add_argument("--by", default=None, metavar="F1,F2",
                    help="group by these fields, pooling the others (e.g. learner or "
                         "env,learner,env.nominal_model; default: the full configuration)")
    rr.add_argument("--confidence", type=float, default=0.95)
    rr.add_argument("--json", default=None, metavar="PATH")
    rr.add_argument("--png", default=None, metavar="PATH")
    rr.add_argument("--markdown", action="store_true", help="a markdown table")

    rp = sub.add_parser("reproduce", help="the paper's Table I, Figs. 2, 4, 6 in simulation")
    rp.add_argument("--quick", action="store_true", help="smaller sizes (< 10 min on 2 cores)")
    rp.add_argument("--json", default=None, metavar="PATH",
                    help="results JSON (default OUT/reproduce.json)")
    rp.add_argument("--out", default=None, metavar="DIR",
                    help="figures, tables and traces (default docs, or reproduce_quick with "
                         "--quick)")
    rp.add_argument("--seed", type=int, default=None)

    pl = sub.add_parser("plot", help="Fig. 2/4/6-like PNGs from reproduce's traces")
    pl.add_argument("--traces", default="docs", metavar="PATH",
                    help="traces.npz written by reproduce, or its folder (default docs)")
    pl.add_argument("--out", default=None, metavar="DIR",
                    help="output folder (default: next to the traces)")

    vd = sub.add_parser("video", help="record a filtered episode (mp4 or gif)")
    vd.add_argument("--env", default=DEFAULT_ENV)
    vd.add_argument("--agent", default="nominal")
    vd.add_argument("--learner", default="auto")
    vd.add_argument("--seed", type=int, default=0)
    vd.add_argument("--max-steps", type=_positive, default=None)
    vd.add_argument("--every", type=_positive, default=5,
                    help="keep one frame in EVERY steps (default 5)")
    vd.add_argument("--out", default="afvsgp_episode.mp4", metavar="PATH",
                    help=".mp4 (imageio-ffmpeg) or .gif")
    vd.add_argument("--env-kwargs", default=None, metavar="JSON")

    tr = sub.add_parser("train", help="train a Stable-Baselines3 agent with the filter in the loop")
    tr.add_argument("--algo", choices=("ppo", "sac"), default="ppo")
    tr.add_argument("--env", default=TRAIN_ENV, help=f"env id (default {TRAIN_ENV}, the RL task)")
    tr.add_argument("--learner", default="auto",
                    help="filter learner (default auto: the env's suggestion, as SafetyFilter)")
    tr.add_argument("--no-filter", action="store_true",
                    help="train on the bare env (no SafetyFilter; overrides --learner)")
    tr.add_argument("--timesteps", type=_positive, default=10_000,
                    help="agent steps (each --action-repeat env steps; default 10000)")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--n-envs", type=_positive, default=1,
                    help="parallel envs, one worker process each when > 1 (SubprocVecEnv)")
    tr.add_argument("--action-repeat", type=_positive, default=None,
                    help="env steps per agent action (default: the env's suggestion, 1 if none)")
    tr.add_argument("--out", default=None, metavar="PATH.zip",
                    help="model zip (default ALGO_ENV_LEARNER.zip)")
    tr.add_argument("--log-dir", default=None, metavar="DIR",
                    help="episodes.csv (one row per episode) and SB3's progress.csv")
    tr.add_argument("--env-kwargs", default=None, metavar="JSON")
    tr.add_argument("--filter-kwargs", default=None, metavar="JSON",
                    help='SafetyFilter options, e.g. \'{"beta": 2.0}\'')
    tr.add_argument("--algo-kwargs", default=None, metavar="JSON",
                    help='PPO/SAC keyword arguments, e.g. \'{"learning_rate": 1e-4}\'')
    tr.add_argument("--verbose", type=int, default=0)

    bn = sub.add_parser("bench", help="speed figures of the GP, env and filter benchmarks")
    bn.add_argument("--quick", action="store_true")
    bn.add_argument("--only", default=None, metavar="A,B",
                    help="subset of gp,envs,filter,arm,solver,sweep")
    rb = sub.add_parser("robot", help="the 1 kHz torque loop on a Franka (libfranka) or its "
                                      "simulated stand-in",
                        description="Run a policy's torques through the safety filter and "
                                    "libfranka's torque-rate limiter at 1 kHz, on a robot "
                                    "(--host, pylibfranka) or on the MuJoCo stand-in with "
                                    "libfranka's interface (--simulate, wall-clock 1 kHz); "
                                    "prints and writes the timing and safety counters "
                                    "(docs/robot.md).")
    rb.add_argument("--simulate", action="store_true", help="the MuJoCo stand-in (dry run)")
    rb.add_argument("--host", default=None, metavar="IP",
                    help="the robot's address (extra 'robot': pylibfranka)")
    rb.add_argument("--seconds", type=float, default=10.0, help="run length (default 10)")
    rb.add_argument("--agent", default=None,
                    help="nominal | hold | zero, or one built to break the filter: ram | "
                         "swing1..swing7 | random (default nominal with --simulate, hold with "
                         "--host)")
    rb.add_argument("--seed", type=int, default=0,
                    help="the swings' first direction and the random torques (default 0)")
    rb.add_argument("--learner", default="none",
                    help="filter learner (default none: the robot's model; a learner's "
                         "updates do not fit in 1 ms here, docs/robot.md)")
    rb.add_argument("--budget", type=float, default=0.9, metavar="MS",
                    help="time from the state to the command before the step falls back "
                         "(default 0.9 ms)")
    rb.add_argument("--torque-error", default="3,3,3,3,1,1,1", metavar="NM",
                    help="bound on the torque the model misses, per joint or one for all "
                         "(default 3,3,3,3,1,1,1 Nm)")
    rb.add_argument("--obstacles", default=None, metavar="JSON",
                    help="obstacles as the envs take them: a JSON list of objects with a "
                         "\"type\" (sphere, box, capsule, plane; docs/environments.md), e.g. "
                         "'[{\"type\": \"plane\", \"position\": [0, 0, 0], \"normal\": "
                         "[0, 0, 1]}]' (a table at the mount), base frame, m; with --simulate "
                         "they replace the stand-in's moving sphere")
    rb.add_argument("--obstacle", action="append", metavar="X,Y,Z,R",
                    help="a fixed sphere in the base frame (m), repeatable; added after "
                         "--obstacles' entries (with --simulate they replace the stand-in's "
                         "moving sphere too)")
    rb.add_argument("--self-collision", action=argparse.BooleanOptionalAction, default=None,
                    help="keep the arm's links apart too (the simulation's 93 self-collision "
                         "barriers; on by default, as in the simulation; --no-self-collision "
                         "turns them off, docs/robot.md)")
    rb.add_argument("--payload", type=float, default=1.0, metavar="KG",
                    help="the stand-in's payload its model does not know (default 1.0)")
    rb.add_argument("--obstacle-noise", type=float, default=0.0, metavar="M",
                    help="the stand-in's camera noise per axis (m, 30 Hz, Kalman estimate with "
                         "covariance; default 0: exact)")
    rb.add_argument("--rt-priority", type=int, default=ROBOT_RT_PRIORITY, metavar="N",
                    help="SCHED_FIFO priority of the loop (default "
                         f"{ROBOT_RT_PRIORITY}; 0: normal priority). Refused, --host stops "
                         "(as libfranka's kEnforce) and --simulate runs at normal priority")
    rb.add_argument("--filter-kwargs", default=None, metavar="JSON",
                    help="SafetyController options over the suggested ones")
    rb.add_argument("--json", default=None, metavar="PATH")
    return p


_COMMANDS = {
    "evaluate": _cmd_evaluate,
    "sweep": _cmd_sweep,
    "report": _cmd_report,
    "reproduce": _cmd_reproduce,
    "plot": _cmd_plot,
    "video": _cmd_video,
    "train": _cmd_train,
    "bench": _cmd_bench,
    "robot": _cmd_robot,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``afvsgp-gym`` console script; returns the exit status.

    Bad arguments raise ``SystemExit(2)`` after printing the valid choices (argparse's
    convention); a missing optional extra exits with status 3.
    """
    parser = build_parser()
    args = parser.parse_args(list(argv) if argv is not None else None)
    subparser = _subparser(parser, args.command)
    return int(_COMMANDS[args.command](args, subparser) or 0)


def _subparser(parser: argparse.ArgumentParser, name: str) -> Any:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices[name]
    return parser  # pragma: no cover


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
