"""Run again, with other env options, the episodes of a results file that reached the brake.

    python benchmarks/rerun_braking.py SOURCE OUT --env-kwargs '{"brake_hold_memory": 0.1}'
    python benchmarks/rerun_braking.py SOURCE OUT --compare   # OUT against SOURCE
    python benchmarks/rerun_braking.py SOURCE OUT --merge     # OUT's runs into SOURCE

Only the brake's behaviour differs between such variants, so an episode whose filter never
fell back to the brake (``infeasible_steps == 0``) runs alike under them and is not run
again. Reads the episodes of ``SOURCE`` (a sweep's records, ``.jsonl`` or ``.jsonl.gz``)
whose filter's learner is one of ``--learners`` (AFVSGP by default), in the envs of
``--envs`` (all by default), and that reached the brake, runs each with ``--env-kwargs``
merged into its env options on ``--workers`` processes, and appends the records to
``OUT``. ``--compare`` prints, per file pair, the episodes with cost under either and the
brake steps per episode. ``--merge`` rewrites ``SOURCE`` with each of its episodes that
``OUT`` ran again replaced by that run, once the options it ran with are the defaults: the
record keeps ``SOURCE``'s ``key``, ``config`` and ``block`` (the same episode at today's
defaults, so a resumed sweep finds it), its own counts and ``code_version``, and names the
options it was given in ``ran_with``.

``benchmarks/results/hold_memory.jsonl.gz`` holds such runs at ``brake_hold_memory=0.1``
(the brake keeps its hold point across feasible gaps while the obstacles stand still) of
``results/scenes.jsonl.gz``, ``results/adversarial.jsonl.gz`` and
``results/acceptance.jsonl.gz``; they were merged into those files when 0.1 became the
default.
"""

from __future__ import annotations

import argparse
import gzip
import json
from multiprocessing import Pool
from pathlib import Path

from docgen import read_jsonl

from afvsgp_gym.evaluation import EpisodeSpec, run_spec


def braking_specs(recs: list[dict], env_kwargs: dict, learners: tuple[str, ...] = ("afvsgp",),
                  envs: tuple[str, ...] = ("",)) -> list[EpisodeSpec]:
    """The episodes of ``recs`` with a filter of ``learners``, in an env whose id contains
    one of ``envs``, that reached the brake, with ``env_kwargs`` merged."""
    out = []
    for r in recs:
        c = r["config"]
        if (c["learner"] in learners and r["infeasible_steps"] > 0
                and any(e in c["env_id"] for e in envs)):
            out.append(EpisodeSpec(c["env_id"], r["seed"], c["learner"], c["agent"],
                                   {**c["env_kwargs"], **env_kwargs}, c["filter_kwargs"],
                                   c["max_steps"]))
    return out


def _key(config: dict, seed: int, drop: set[str]) -> str:
    env_kwargs = {k: v for k, v in config["env_kwargs"].items() if k not in drop}
    return json.dumps([config["env_id"], config["learner"], config["agent"], env_kwargs,
                       config["filter_kwargs"], seed], sort_keys=True)


def _added_options(source: list[dict], out: list[dict]) -> set[str]:
    """The env options ``out``'s runs were given that ``source``'s never name."""
    return {k for r in out for k in r["config"]["env_kwargs"]} - {
        k for r in source for k in r["config"]["env_kwargs"]}


def compare(source: list[dict], out: list[dict]) -> None:
    """Print the episodes with cost under either file and the brake steps per episode (the
    records of ``out`` that run an episode of ``source``; others are left out)."""
    drop = _added_options(source, out)
    old = {_key(r["config"], r["seed"], set()): r for r in source}
    pairs = [(old[k], r) for r in out if (k := _key(r["config"], r["seed"], drop)) in old]
    for before, after in pairs:
        if before["cost_steps"] or after["cost_steps"]:
            c = after["config"]
            print(f"{c['env_id']} {c['agent']} {c['env_kwargs']} seed {after['seed']}: cost "
                  f"steps {before['cost_steps']} -> {after['cost_steps']}, min h "
                  f"{100 * before['min_h']:+.2f} -> {100 * after['min_h']:+.2f} cm")
    n = len(pairs)
    print(f"{n} episodes; with cost {sum(b['cost_steps'] > 0 for b, _ in pairs)} -> "
          f"{sum(a['cost_steps'] > 0 for _, a in pairs)}; brake steps per episode "
          f"{sum(b['infeasible_steps'] for b, _ in pairs) / max(n, 1):.1f} -> "
          f"{sum(a['infeasible_steps'] for _, a in pairs) / max(n, 1):.1f}")


def merge(source: list[dict], out: list[dict]) -> tuple[list[dict], int]:
    """``source`` with its episodes that ``out`` ran again replaced (see the module
    docstring), and how many were replaced."""
    added = _added_options(source, out)
    reruns = {_key(r["config"], r["seed"], added): r for r in out}
    merged, n = [], 0
    for r in source:
        new = reruns.get(_key(r["config"], r["seed"], set()))
        if new is None:
            merged.append(r)
            continue
        ran_with = {k: new["config"]["env_kwargs"][k] for k in sorted(added)
                    if k in new["config"]["env_kwargs"]}
        c = r["config"]
        key = r.get("key") or EpisodeSpec(c["env_id"], r["seed"], c["learner"], c["agent"],
                                          c["env_kwargs"], c["filter_kwargs"],
                                          c["max_steps"]).key()
        merged.append({**new, "key": key, "config": c, "ran_with": ran_with,
                       **({"block": r["block"]} if "block" in r else {})})
        n += 1
    return merged, n


def write(path: Path, recs: list[dict]) -> None:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "wt") as f:
        f.writelines(json.dumps(r) + "\n" for r in recs)


def _run(spec: EpisodeSpec) -> dict:
    return run_spec(spec)[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--env-kwargs", default="{}", help="JSON merged into each env's options")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--learners", default="afvsgp",
                   help="comma-separated filter learners whose episodes run again")
    p.add_argument("--envs", default="",
                   help="comma-separated parts of the env ids whose episodes run again "
                        "(default: every env)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--compare", action="store_true", help="compare OUT with SOURCE only")
    mode.add_argument("--merge", action="store_true",
                      help="replace SOURCE's episodes that OUT ran again by those runs")
    args = p.parse_args()
    if args.workers < 1:
        p.error(f"--workers must be >= 1, got {args.workers}")
    try:
        env_kwargs = json.loads(args.env_kwargs)
    except json.JSONDecodeError as exc:
        p.error(f"--env-kwargs must be a JSON object: {exc}")
    if not isinstance(env_kwargs, dict):
        p.error(f"--env-kwargs must be a JSON object, got {args.env_kwargs!r}")
    if not (args.compare or args.merge) and args.out.suffix == ".gz":
        p.error("OUT is appended to line by line: give a plain .jsonl (gzip it after)")
    source = read_jsonl(args.source)
    if args.compare:
        compare(source, read_jsonl(args.out))
        return
    if args.merge:
        merged, n = merge(source, read_jsonl(args.out))
        write(args.source, merged)
        print(f"{args.source}: {n} of {len(merged)} episodes replaced")
        return
    specs = braking_specs(source, env_kwargs,
                          tuple(args.learners.split(",")), tuple(args.envs.split(",")))
    print(f"{len(specs)} episodes", flush=True)
    with Pool(args.workers) as pool, open(args.out, "a") as f:
        for rec in pool.imap_unordered(_run, specs):
            f.write(json.dumps(rec) + "\n")
            f.flush()


if __name__ == "__main__":
    main()
