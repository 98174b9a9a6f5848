"""Run again, with other env options, the episodes of a results file that reached the brake.

    python benchmarks/rerun_braking.py SOURCE OUT --env-kwargs '{"brake_hold_memory": 0.1}'
    python benchmarks/rerun_braking.py SOURCE OUT --compare   # OUT against SOURCE

Only the brake's behaviour differs between such variants, so an episode whose filter never
fell back to the brake (``infeasible_steps == 0``) runs alike under them and is not run
again. Reads the AFVSGP episodes of ``SOURCE`` (a sweep's records, ``.jsonl`` or
``.jsonl.gz``) that reached the brake, runs each with ``--env-kwargs`` merged into its env
options on ``--workers`` processes, and appends the records to ``OUT``. ``--compare``
prints, per file pair, the episodes with cost under either and the brake steps per episode.

``benchmarks/results/hold_memory.jsonl.gz`` holds such runs at ``brake_hold_memory=0.1``
(the brake keeps its hold point across feasible gaps while the obstacles stand still) of
``results/scenes.jsonl.gz``, ``results/adversarial.jsonl.gz`` and
``results/acceptance.jsonl.gz``.
"""

from __future__ import annotations

import argparse
import gzip
import json
from multiprocessing import Pool
from pathlib import Path

from afvsgp_gym.evaluation import EpisodeSpec, run_spec


def read(path: Path) -> list[dict]:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        return [json.loads(line) for line in f if line.strip()]


def braking_specs(recs: list[dict], env_kwargs: dict) -> list[EpisodeSpec]:
    """The AFVSGP episodes of ``recs`` that reached the brake, with ``env_kwargs`` merged."""
    out = []
    for r in recs:
        c = r["config"]
        if c["learner"] == "afvsgp" and r["infeasible_steps"] > 0:
            out.append(EpisodeSpec(c["env_id"], r["seed"], c["learner"], c["agent"],
                                   {**c["env_kwargs"], **env_kwargs}, c["filter_kwargs"],
                                   c["max_steps"]))
    return out


def _key(config: dict, seed: int, drop: set[str]) -> str:
    env_kwargs = {k: v for k, v in config["env_kwargs"].items() if k not in drop}
    return json.dumps([config["env_id"], config["agent"], env_kwargs,
                       config["filter_kwargs"], seed], sort_keys=True)


def compare(source: list[dict], out: list[dict]) -> None:
    """Print the episodes with cost under either file and the brake steps per episode (the
    records of ``out`` that run an episode of ``source``; others are left out)."""
    drop = {k for r in out for k in r["config"]["env_kwargs"]} - {
        k for r in source for k in r["config"]["env_kwargs"]}
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


def _run(spec: EpisodeSpec) -> dict:
    return run_spec(spec)[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--env-kwargs", default="{}", help="JSON merged into each env's options")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--compare", action="store_true", help="compare OUT with SOURCE only")
    args = p.parse_args()
    source = read(args.source)
    if args.compare:
        compare(source, read(args.out))
        return
    specs = braking_specs(source, json.loads(args.env_kwargs))
    print(f"{len(specs)} episodes", flush=True)
    with Pool(args.workers) as pool, open(args.out, "a") as f:
        for rec in pool.imap_unordered(_run, specs):
            f.write(json.dumps(rec) + "\n")
            f.flush()


if __name__ == "__main__":
    main()
