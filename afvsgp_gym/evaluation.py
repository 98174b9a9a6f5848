"""Seeded evaluation of an agent behind the safety filter, with a per-episode safety report.

One public function, :func:`evaluate`, runs ``episodes`` episodes per learner on the same seeds
(episode ``i`` is reset with ``seed + i`` and gets a fresh environment and filter, so episodes are
independent and learners are compared on identical scenarios) and returns::

    {"episodes": [record, ...], "summary": {learner: {...}, ...}}

Each record holds the return, the number of steps with ``h < 0`` (violation steps, from
``info["h"]``), the minimum of ``h``, the number of collision steps, the number of filter
interventions (``info["filter_active"]``), infeasible steps (``not info["filter_feasible"]``) and
the median and 99th percentile of ``info["filter_time_s"]``. :func:`write_json`,
:func:`write_csv` and :func:`format_table` render the result.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "EPISODE_FIELDS",
    "SUMMARY_FIELDS",
    "check_writable",
    "evaluate",
    "format_table",
    "make_policy",
    "run_episode",
    "summarize",
    "write_csv",
    "write_json",
]

#: Keys of one episode record, in table / CSV column order.
EPISODE_FIELDS = (
    "learner",
    "episode",
    "seed",
    "steps",
    "return",
    "violation_steps",
    "min_h",
    "collisions",
    "interventions",
    "infeasible_steps",
    "filter_time_median_s",
    "filter_time_p99_s",
)

#: Keys of one learner's summary.
SUMMARY_FIELDS = (
    "episodes",
    "steps",
    "return_mean",
    "return_std",
    "violation_steps",
    "episodes_with_violations",
    "min_h",
    "collisions",
    "interventions",
    "infeasible_steps",
    "filter_time_median_s",
    "filter_time_p99_s",
)

BUILTIN_AGENTS = ("nominal", "random")

Policy = Callable[[np.ndarray], np.ndarray]


def check_writable(path: str | os.PathLike, *, directory: bool = False) -> Path:
    """Fail fast (``ValueError``) when ``path`` cannot be written; returns it as a Path.

    For a file, its parent folder is created if needed and a probe file is written and removed;
    for a directory (``directory=True``) the folder itself is created and probed.
    """
    p = Path(path)
    folder = p if directory else p.parent
    if not directory and p.is_dir():
        raise ValueError(f"output path {str(p)!r} is a directory, expected a file path")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".afvsgp_write_probe_{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        if not directory and p.exists() and not os.access(p, os.W_OK):
            raise PermissionError(f"{p} is read-only")
    except OSError as exc:
        raise ValueError(f"output path {str(p)!r} is not writable: {exc}") from None
    return p


def make_policy(agent: str, env: Any, seed: int | None = None) -> Policy:
    """Build an ``obs -> action`` callable for ``agent``.

    ``"nominal"``: :class:`afvsgp_gym.agents.NominalController` (ignores obstacles, the filter's
    u_nom); ``"random"``: uniform samples of the action space seeded by ``seed``; a path ending in
    ``.zip``: a Stable-Baselines3 model (deterministic actions, see :mod:`afvsgp_gym.agents.sb3`).
    """
    if agent == "nominal":
        from afvsgp_gym.agents import NominalController

        return NominalController(env)
    if agent == "random":
        space = env.action_space
        space.seed(seed)
        return lambda obs: space.sample()
    if str(agent).endswith(".zip"):
        from afvsgp_gym.agents.sb3 import load_policy

        return load_policy(agent, env=env)
    raise ValueError(
        f"agent must be one of {', '.join(BUILTIN_AGENTS)} or a path to a Stable-Baselines3 "
        f".zip file, got {agent!r}"
    )


def run_episode(
    env: Any,
    policy: Policy,
    seed: int,
    *,
    max_steps: int | None = None,
    trace: bool = False,
    on_step: Callable[[dict], None] | None = None,
) -> tuple[dict, dict | None]:
    """Run one episode from ``env.reset(seed=seed)``; returns ``(record, trace)``.

    ``record`` has the keys of :data:`EPISODE_FIELDS` except ``learner``/``episode`` (the caller's)
    plus the raw ``"_filter_times"`` list. ``trace`` (when asked) holds per-step arrays ``t``,
    ``h``, ``delta_b_true``, ``delta_b_mean``, ``delta_b_std``, ``filter_active``.
    ``on_step(info)`` (optional) is called after every step with the step's ``info``.
    """
    obs, info = env.reset(seed=int(seed))
    dt = float(getattr(env.unwrapped, "dt", 1.0))
    ret = 0.0
    steps = violations = collisions = interventions = infeasible = 0
    min_h = math.inf
    times: list[float] = []
    tr: dict[str, list] = {k: [] for k in ("h", "delta_b_true", "delta_b_mean", "delta_b_std",
                                           "filter_active")}
    while True:
        action = policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        steps += 1
        ret += float(reward)
        h = float(info.get("h", math.nan))
        if h < 0.0:
            violations += 1
        if h < min_h:
            min_h = h
        collisions += int(bool(info.get("collision", False)))
        interventions += int(bool(info.get("filter_active", False)))
        infeasible += int(not bool(info.get("filter_feasible", True)))
        if "filter_time_s" in info:
            times.append(float(info["filter_time_s"]))
        if trace:
            tr["h"].append(h)
            tr["delta_b_true"].append(_first(info.get("delta_b_true")))
            tr["delta_b_mean"].append(_first(info.get("delta_b_mean")))
            tr["delta_b_std"].append(_first(info.get("delta_b_std")))
            tr["filter_active"].append(bool(info.get("filter_active", False)))
        if on_step is not None:
            on_step(info)
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            break
    record = {
        "seed": int(seed),
        "steps": steps,
        "return": ret,
        "violation_steps": violations,
        "min_h": min_h,
        "collisions": collisions,
        "interventions": interventions,
        "infeasible_steps": infeasible,
        "filter_time_median_s": float(np.median(times)) if times else math.nan,
        "filter_time_p99_s": float(np.percentile(times, 99)) if times else math.nan,
        "_filter_times": times,
    }
    trace_out = None
    if trace:
        trace_out = {k: np.asarray(v, dtype=float) for k, v in tr.items()}
        trace_out["t"] = dt * np.arange(1, steps + 1)
    return record, trace_out


def _first(x: Any) -> float:
    """First entry of a per-obstacle array (or a scalar); NaN when absent."""
    if x is None:
        return math.nan
    a = np.ravel(np.asarray(x, dtype=float))
    return float(a[0]) if a.size else math.nan


def summarize(records: Iterable[dict], filter_times: Sequence[float] = ()) -> dict:
    """Aggregate episode records of one learner; filter-time quantiles pool every step."""
    records = list(records)
    returns = np.array([r["return"] for r in records], dtype=float)
    times = np.asarray(filter_times, dtype=float)
    return {
        "episodes": len(records),
        "steps": int(sum(r["steps"] for r in records)),
        "return_mean": float(returns.mean()) if records else math.nan,
        "return_std": float(returns.std()) if records else math.nan,
        "violation_steps": int(sum(r["violation_steps"] for r in records)),
        "episodes_with_violations": int(sum(r["violation_steps"] > 0 for r in records)),
        "min_h": float(min((r["min_h"] for r in records), default=math.nan)),
        "collisions": int(sum(r["collisions"] for r in records)),
        "interventions": int(sum(r["interventions"] for r in records)),
        "infeasible_steps": int(sum(r["infeasible_steps"] for r in records)),
        "filter_time_median_s": float(np.median(times)) if times.size else math.nan,
        "filter_time_p99_s": float(np.percentile(times, 99)) if times.size else math.nan,
    }


def evaluate(
    env_id: str,
    *,
    agent: str = "nominal",
    learners: Sequence[str | None] = ("afvsgp",),
    episodes: int = 3,
    seed: int = 0,
    max_steps: int | None = None,
    env_kwargs: dict | None = None,
    filter_kwargs: dict | None = None,
    progress: bool = False,
    traces: bool = False,
) -> dict:
    """Evaluate ``agent`` behind ``SafetyFilter(learner=...)`` for each learner, same seeds.

    Parameters
    ----------
    env_id : a registered ``afvsgp_gym/...`` id.
    agent : ``"nominal"``, ``"random"`` or a path to a Stable-Baselines3 ``.zip``.
    learners : filter learner names (``afvsgp_gym.cbf.LEARNERS``); ``None`` runs the bare env.
    episodes, seed : episode ``i`` is reset with ``seed + i``, in a fresh env and filter (whose
        warm-up exploration noise is seeded with the same number unless ``filter_kwargs`` sets
        ``seed``).
    max_steps : optional cap on steps per episode (below the registered time limit).
    progress : show a tqdm bar (steps) on stderr.
    traces : also return per-step traces under ``"traces"`` (``{learner: [trace, ...]}``).

    Returns
    -------
    dict ``{"episodes": [...], "summary": {learner: {...}}}`` (plus ``"traces"`` if asked).
    """
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401  (registers the ids)

    if episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes}")
    env_kwargs = dict(env_kwargs or {})
    filter_kwargs = dict(filter_kwargs or {})
    spec = gym.spec(env_id)
    per_ep = spec.max_episode_steps or 1000
    if max_steps is not None:
        per_ep = min(per_ep, int(max_steps))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=per_ep * episodes * len(learners), unit="step", desc="evaluate",
                   dynamic_ncols=True, mininterval=0.5, file=sys.stderr)
    out_records: list[dict] = []
    summary: dict[str, dict] = {}
    all_traces: dict[str, list] = {}
    try:
        for learner in learners:
            name = "unfiltered" if learner is None else str(learner)
            recs, times = [], []
            for i in range(episodes):
                ep_seed = int(seed) + i
                fkw = {"seed": ep_seed, **filter_kwargs}  # seeded warm-up exploration
                env = _make_env(env_id, learner, env_kwargs, fkw)
                try:
                    policy = make_policy(agent, env, seed=ep_seed)
                    if bar is not None:
                        bar.set_postfix_str(f"{name} ep {i + 1}/{episodes}")
                    tick = None if bar is None else (lambda _info: bar.update(1))
                    rec, tr = run_episode(env, policy, ep_seed, max_steps=max_steps, trace=traces,
                                          on_step=tick)
                finally:
                    env.close()
                if bar is not None:  # account for episodes that ended before the cap
                    bar.update(max(per_ep - rec["steps"], 0))
                times.extend(rec.pop("_filter_times"))
                rec = {"learner": name, "episode": i, **rec}
                recs.append({k: rec[k] for k in EPISODE_FIELDS})
                if traces:
                    all_traces.setdefault(name, []).append(tr)
            out_records.extend(recs)
            summary[name] = summarize(recs, times)
    finally:
        if bar is not None:
            bar.close()
    result: dict[str, Any] = {"episodes": out_records, "summary": summary}
    if traces:
        result["traces"] = all_traces
    return result


def _make_env(env_id: str, learner: str | None, env_kwargs: dict, filter_kwargs: dict) -> Any:
    import gymnasium as gym

    env = gym.make(env_id, **env_kwargs)
    if learner is None:
        return env
    from afvsgp_gym.wrappers import SafetyFilter

    return SafetyFilter(env, learner=learner, **filter_kwargs)


# ---------------------------------------------------------------------------------------------
# Rendering


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        v = float(v)
        if math.isnan(v):
            return "-"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return f"{v:.4g}"
    return str(v)


_TIME_KEYS = ("filter_time_median_s", "filter_time_p99_s")


def _table(rows: list[dict], cols: Sequence[str], headers: Sequence[str]) -> str:
    cells = [[_fmt(r[c] * 1e6 if c in _TIME_KEYS and isinstance(r[c], float) else r[c])
              for c in cols] for r in rows]
    widths = [max(len(h), *(len(row[j]) for row in cells)) if cells else len(h)
              for j, h in enumerate(headers)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)


def format_table(result: dict) -> str:
    """Per-episode table followed by the per-learner summary (filter times in microseconds)."""
    ep_cols = EPISODE_FIELDS
    ep_head = ("learner", "ep", "seed", "steps", "return", "viol", "min_h", "coll", "interv",
               "infeas", "t_med_us", "t_p99_us")
    sum_rows = [{"learner": k, **v} for k, v in result["summary"].items()]
    sum_cols = ("learner",) + SUMMARY_FIELDS
    sum_head = ("learner", "episodes", "steps", "return", "return_std", "viol", "eps_viol",
                "min_h", "coll", "interv", "infeas", "t_med_us", "t_p99_us")
    return ("Episodes\n" + _table(result["episodes"], ep_cols, ep_head)
            + "\n\nSummary\n" + _table(sum_rows, sum_cols, sum_head))


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    if isinstance(x, float | np.floating):
        x = float(x)
        return x if math.isfinite(x) else None  # strict JSON: NaN/inf become null
    return x


def write_json(result: dict, path: str | os.PathLike) -> None:
    """Write ``{"episodes": [...], "summary": {...}}`` (non-finite floats as null)."""
    data = {k: v for k, v in result.items() if k != "traces"}
    Path(path).write_text(json.dumps(_jsonable(data), indent=2) + "\n")


def write_csv(result: dict, path: str | os.PathLike) -> None:
    """Write one CSV row per episode with the columns of :data:`EPISODE_FIELDS`."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(EPISODE_FIELDS))
        w.writeheader()
        for r in result["episodes"]:
            w.writerow({k: r[k] for k in EPISODE_FIELDS})
