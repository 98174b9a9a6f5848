"""The one episode runner: seeded episodes of an agent behind the safety filter, counted.

An episode is an :class:`EpisodeSpec` (env id and kwargs, learner and filter kwargs, agent,
seed, step cap); :func:`run_spec` builds a fresh env and filter, runs it with
:func:`run_episode` and returns a JSON-able record, deterministic given the spec whatever the
process it runs in (the env is reset with the seed and the filter's exploration noise is seeded
with it). ``evaluate`` and ``afvsgp-gym sweep`` both run episodes this way, through the
executors of :mod:`afvsgp_gym.executors` (in-process, a local process pool, or Ray).

Per episode (see :data:`EPISODE_FIELDS`): ``cost_steps`` (``info["cost"] > 0``, see
:data:`COST_DEFINITION`), and by kind ``violation_steps`` (``info["h"] < 0``), ``contact_steps``
(``info["collision"]``), ``limit_steps`` (``info["limit_violation"]``), ``min_h``,
``interventions`` (``info["filter_active"]``),
``infeasible_steps`` (``not info["filter_feasible"]``: the filter applied its backup),
``tracking_error_mean``/``_max`` over the steps after the env's warm-up whose reference keeps
``info["reference_h"] >= REFERENCE_CLEARANCE`` from every obstacle (NaN when no step does or
the env reports neither), filter time median and 99th percentile. The headline safety number
of a set of episodes is the number of episodes with cost, with its Clopper-Pearson bound
(:func:`summarize`).
"""

from __future__ import annotations

import csv
import functools
import hashlib
import json
import math
import os
import subprocess
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "BUILTIN_AGENTS",
    "COST_DEFINITION",
    "EPISODE_FIELDS",
    "REFERENCE_CLEARANCE",
    "SUMMARY_FIELDS",
    "UNFILTERED",
    "EpisodeSpec",
    "check_writable",
    "code_version",
    "cpu_model",
    "evaluate",
    "format_table",
    "jsonable",
    "make_policy",
    "run_episode",
    "run_spec",
    "summarize",
    "write_csv",
    "write_json",
]

#: Counted columns of one episode (records of :func:`run_spec` hold them all).
COUNT_FIELDS = (
    "steps",
    "return",
    "cost_steps",
    "violation_steps",
    "contact_steps",
    "limit_steps",
    "min_h",
    "interventions",
    "infeasible_steps",
    "tracking_error_mean",
    "tracking_error_max",
    "unstable",
    "safe_proposals",
    "safe_proposals_kept",
    "filter_time_median_s",
    "filter_time_p99_s",
)

#: Keys of one ``evaluate`` episode row, in table / CSV column order.
EPISODE_FIELDS = ("learner", "episode", "seed", *COUNT_FIELDS)

#: Keys of one summary (:func:`summarize`), in table order.
SUMMARY_FIELDS = (
    "episodes",
    "episodes_with_cost",
    "cost_rate_upper",
    "episodes_with_violation",
    "episodes_with_contact",
    "episodes_with_limit_violation",
    "cost_steps",
    "violation_steps",
    "contact_steps",
    "limit_steps",
    "min_h",
    "interventions",
    "infeasible_steps",
    "tracking_error_mean",
    "tracking_error_max",
    "return_mean",
    "return_std",
    "steps",
    "unstable_episodes",
    "minimal_intervention",
    "filter_time_median_s",
    "filter_time_p99_s",
)

#: The name of "no filter" where a learner name is expected (``--compare``, sweep configs).
UNFILTERED = "unfiltered"

#: The one definition of the safety cost, printed with every table.
COST_DEFINITION = (
    "cost: steps with info['cost'] > 0, i.e. some obstacle barrier has h < 0 (h<0), the robot "
    "touches an obstacle (contact), or a joint is at its range stop or above its speed limit "
    "(limits; with the env's optional checks also above its acceleration or torque-rate limit)"
)

#: m/s^2; a proposal is "safe with margin" when its true HOCBF constraint value exceeds this
#: for every barrier (``info["proposal_true_margin"]``, the minimal-intervention count).
SAFE_MARGIN = 2.0

#: Agents by name: the obstacle-blind tracker, uniform random actions and the adversarial
#: policies of :mod:`afvsgp_gym.agents.adversarial` (Franka torque envs).
BUILTIN_AGENTS = ("nominal", "random", "ram", *(f"swing{j}" for j in range(1, 8)), "greedy",
                  "untrained-ppo")

#: m; tracking error counts where the reference's ee sphere keeps this clearance (reference_h).
REFERENCE_CLEARANCE = 0.05

Policy = Callable[[np.ndarray], np.ndarray]


# ----------------------------------------------------------------------------- the episode


@dataclass(frozen=True)
class EpisodeSpec:
    """Everything that determines one episode.

    ``learner=None`` runs the bare env (no filter). ``filter_kwargs`` go to
    :class:`afvsgp_gym.wrappers.SafetyFilter`; unless they set ``seed``, the filter is seeded
    with the episode seed. ``max_steps`` caps the episode below the env's time limit.
    """

    env_id: str
    seed: int
    learner: str | None = "afvsgp"
    agent: str = "nominal"
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    filter_kwargs: Mapping[str, Any] = field(default_factory=dict)
    max_steps: int | None = None

    def config(self) -> dict[str, Any]:
        """The spec without its seed, as plain JSON data (kwargs with sorted keys)."""
        return {
            "env_id": self.env_id,
            "env_kwargs": jsonable(dict(sorted(self.env_kwargs.items()))),
            "learner": self.learner,
            "filter_kwargs": jsonable(dict(sorted(self.filter_kwargs.items()))),
            "agent": self.agent,
            "max_steps": self.max_steps,
        }

    def key(self) -> str:
        """SHA-256 of the canonical JSON of the config and the seed: the episode's identity
        (an object JSON cannot hold, e.g. a callable ``backup``, enters by its ``repr``)."""
        text = json.dumps({**self.config(), "seed": int(self.seed)}, sort_keys=True,
                          separators=(",", ":"), allow_nan=False, default=repr)
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def learner_name(self) -> str:
        return UNFILTERED if self.learner is None else str(self.learner)


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """``git describe --always --dirty --tags`` of the package's checkout, else its version."""
    import afvsgp_gym

    root = Path(afvsgp_gym.__file__).resolve().parent.parent
    if (root / ".git").exists():
        try:
            out = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty",
                                  "--tags"], capture_output=True, text=True, timeout=10)
            if out.returncode == 0 and out.stdout.strip():
                return out.stdout.strip()
        except (OSError, subprocess.SubprocessError):
            pass
    return str(afvsgp_gym.__version__)


@functools.lru_cache(maxsize=1)
def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where present, else the platform's)."""
    import platform

    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def make_policy(agent: str, env: Any, seed: int | None = None) -> Policy:
    """Build an ``obs -> action`` callable for ``agent``.

    ``"nominal"``: :class:`afvsgp_gym.agents.NominalController` (ignores obstacles, the filter's
    u_nom); ``"random"``: uniform samples of the action space seeded by ``seed``; ``"ram"``,
    ``"swing1"`` .. ``"swing7"``, ``"greedy"``, ``"untrained-ppo"``: the adversarial policies of
    :mod:`afvsgp_gym.agents.adversarial`; a path ending in ``.zip``: a Stable-Baselines3 model
    (deterministic actions, see :mod:`afvsgp_gym.agents.sb3`).
    """
    if agent == "nominal":
        from afvsgp_gym.agents import NominalController

        return NominalController(env)
    if agent == "random":
        space = env.action_space
        space.seed(seed)
        return lambda obs: space.sample()
    from afvsgp_gym.agents.adversarial import ADVERSARIAL_AGENTS

    if agent in ADVERSARIAL_AGENTS:
        return ADVERSARIAL_AGENTS[agent](env, seed=seed)
    if str(agent).endswith(".zip"):
        from afvsgp_gym.agents.sb3 import load_policy

        return load_policy(agent, env=env)
    raise ValueError(
        f"agent must be one of {', '.join(BUILTIN_AGENTS)} or a path to a Stable-Baselines3 "
        f".zip file, got {agent!r}"
    )


def make_env(spec: EpisodeSpec) -> Any:
    """A fresh env for ``spec``, behind ``SafetyFilter`` unless ``spec.learner`` is None."""
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401  (registers the ids)

    env = gym.make(spec.env_id, **dict(spec.env_kwargs))
    if spec.learner is None:
        return env
    from afvsgp_gym.wrappers import SafetyFilter

    fkw = {"seed": int(spec.seed), **dict(spec.filter_kwargs)}  # seeded exploration noise
    return SafetyFilter(env, learner=spec.learner, **fkw)


def _reference_h(base: Any) -> float:
    """Clearance of the reference's sphere from every obstacle, for envs whose info lacks
    ``reference_h`` (h of a sphere of the agent's radius placed at the reference)."""
    ref, obstacles = getattr(base, "reference", None), getattr(base, "obstacles", None)
    radius = getattr(base, "ee_radius", getattr(base, "agent_radius", None))
    if ref is None or obstacles is None or radius is None:
        return math.nan
    t = float(base.time)
    r = ref.state(t)[0]
    return min((float(np.linalg.norm(r - ob.state(t)[0])) - ob.radius - radius
                for ob in obstacles), default=math.inf)


def _tracking(base: Any, info: Mapping[str, Any]) -> tuple[float, float]:
    """(tracking error m, reference clearance m) of a step; NaN where the env has neither."""
    err = info.get("tracking_error")
    if err is None:
        weight = getattr(base, "tracking_weight", None)
        err = (-info["reward_tracking"] / weight if weight and "reward_tracking" in info
               else math.nan)
    ref_h = info.get("reference_h")
    if ref_h is None:
        ref_h = _reference_h(base)
    return float(err), float(ref_h)


def run_episode(
    env: Any,
    policy: Policy,
    seed: int,
    *,
    max_steps: int | None = None,
    trace: bool = False,
    on_step: Callable[[dict], None] | None = None,
) -> tuple[dict, dict | None]:
    """Run one episode from ``env.reset(seed=seed)``; returns ``(counts, trace)``.

    ``counts`` has the keys of :data:`COUNT_FIELDS` plus ``"filter_time_hist"`` (the step
    times as a :func:`afvsgp_gym.stats.time_histogram`). ``trace`` (when asked) holds per-step
    arrays ``t``, ``h``, ``delta_b_true``, ``delta_b_mean``, ``delta_b_std`` (first barrier),
    ``filter_active``. ``on_step(info)`` (optional) is called after every step.
    """
    from afvsgp_gym.stats import time_histogram

    obs, info = env.reset(seed=int(seed))
    base = env.unwrapped
    dt = float(getattr(base, "dt", 1.0))
    warmup_steps = int(getattr(base, "warmup_steps", 0) or 0)
    ret = 0.0
    steps = cost = violations = contacts = limits = interventions = infeasible = 0
    safe = kept = 0
    unstable = False
    min_h = math.inf
    times: list[float] = []
    track: list[float] = []
    tr: dict[str, list] = {k: [] for k in ("h", "delta_b_true", "delta_b_mean", "delta_b_std",
                                           "filter_active")}
    while True:
        action = policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        steps += 1
        ret += float(reward)
        h = float(info.get("h", math.nan))
        cost += int(float(info.get("cost", 0.0)) > 0.0)
        violations += int(h < 0.0)
        min_h = min(min_h, h)
        contacts += int(bool(info.get("collision", False)))
        limits += int(bool(info.get("limit_violation", False)))
        interventions += int(bool(info.get("filter_active", False)))
        infeasible += int(not bool(info.get("filter_feasible", True)))
        unstable |= bool(info.get("unstable", False))
        if not info.get("warmup", True) and info.get("proposal_true_margin", -1.0) > SAFE_MARGIN:
            safe += 1
            kept += bool(np.array_equal(info["action_applied"], np.asarray(
                info["action_proposed"]).astype(np.asarray(info["action_applied"]).dtype)))
        if "filter_time_s" in info:
            times.append(float(info["filter_time_s"]))
        err, ref_h = _tracking(base, info)
        if steps > warmup_steps and ref_h >= REFERENCE_CLEARANCE and math.isfinite(err):
            track.append(err)
        if trace:
            tr["h"].append(h)
            for k in ("delta_b_true", "delta_b_mean", "delta_b_std"):
                tr[k].append(_first(info.get(k)))
            tr["filter_active"].append(bool(info.get("filter_active", False)))
        if on_step is not None:
            on_step(info)
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            break
    counts = {
        "steps": steps,
        "return": ret,
        "cost_steps": cost,
        "violation_steps": violations,
        "contact_steps": contacts,
        "limit_steps": limits,
        "min_h": min_h,
        "interventions": interventions,
        "infeasible_steps": infeasible,
        "tracking_error_mean": float(np.mean(track)) if track else math.nan,
        "tracking_error_max": float(np.max(track)) if track else math.nan,
        "unstable": unstable,
        "safe_proposals": safe,
        "safe_proposals_kept": kept,
        "filter_time_median_s": float(np.median(times)) if times else math.nan,
        "filter_time_p99_s": float(np.percentile(times, 99)) if times else math.nan,
        "filter_time_hist": time_histogram(times),
    }
    trace_out = None
    if trace:
        trace_out = {k: np.asarray(v, dtype=float) for k, v in tr.items()}
        trace_out["t"] = dt * np.arange(1, steps + 1)
    return counts, trace_out


def _first(x: Any) -> float:
    """First entry of a per-barrier array (or a scalar); NaN when absent."""
    if x is None:
        return math.nan
    a = np.ravel(np.asarray(x, dtype=float))
    return float(a[0]) if a.size else math.nan


def run_spec(spec: EpisodeSpec, trace: bool = False) -> tuple[dict, dict | None]:
    """Run one episode in a fresh env and filter; returns ``(record, trace)``.

    The record (JSON-able) holds ``key``, ``config``, ``seed``, ``code_version``, the counts of
    :func:`run_episode`, ``wall_s`` and ``cpu_s`` (construction and run, wall-clock and CPU
    time of the worker), ``host``, ``machine`` (the CPU model) and ``date`` (the day it ran).
    This is the task every executor runs.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    env = make_env(spec)
    try:
        policy = make_policy(spec.agent, env, seed=spec.seed)
        counts, tr = run_episode(env, policy, spec.seed, max_steps=spec.max_steps, trace=trace)
    finally:
        env.close()
    record = {
        "key": spec.key(),
        "config": spec.config(),
        "seed": int(spec.seed),
        "code_version": code_version(),
        **counts,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "host": os.uname().nodename if hasattr(os, "uname") else "",
        "machine": cpu_model(),
        "date": time.strftime("%Y-%m-%d"),
    }
    return jsonable(record), tr


# ----------------------------------------------------------------------------- aggregation


def _num(x: Any) -> float:
    return math.nan if x is None else float(x)


def summarize(records: Iterable[Mapping[str, Any]], confidence: float = 0.95) -> dict:
    """Aggregate episode records (of :func:`run_spec` or ``evaluate`` rows).

    Counts are summed over episodes; ``episodes_with_cost`` is the headline with
    ``cost_rate_upper`` its exact one-sided Clopper-Pearson ``confidence`` bound;
    ``tracking_error_mean`` is the mean of the episode means (episodes without a counted step
    left out), ``min_h`` and ``tracking_error_max`` the extremes; ``minimal_intervention`` the
    share of the proposals that were safe with margin (true HOCBF constraint above
    :data:`SAFE_MARGIN` after warm-up) and passed the filter unchanged; filter times are
    quantiles of every step pooled (from the records' histograms when present).
    """
    from afvsgp_gym.stats import clopper_pearson_upper, histogram_quantile, merge_histograms

    records = list(records)
    n = len(records)
    if n == 0:
        raise ValueError("summarize needs at least one episode record")
    returns = np.array([_num(r["return"]) for r in records])
    track = np.array([_num(r["tracking_error_mean"]) for r in records])
    track_max = np.array([_num(r["tracking_error_max"]) for r in records])
    with_cost = sum(int(r["cost_steps"]) > 0 for r in records)
    safe_total = sum(int(r.get("safe_proposals") or 0) for r in records)
    kept_total = sum(int(r.get("safe_proposals_kept") or 0) for r in records)
    hists = [r.get("filter_time_hist") for r in records]
    if all(h is not None for h in hists):
        hist = merge_histograms(hists)
        t_med, t_p99 = histogram_quantile(hist, 0.5), histogram_quantile(hist, 0.99)
    else:  # rows without histograms: episode quantiles only
        t_med = float(np.nanmedian([_num(r["filter_time_median_s"]) for r in records]))
        t_p99 = float(np.nanmax([_num(r["filter_time_p99_s"]) for r in records]))
    return {
        "episodes": n,
        "episodes_with_cost": int(with_cost),
        "cost_rate_upper": clopper_pearson_upper(int(with_cost), n, confidence),
        "episodes_with_violation": int(sum(int(r["violation_steps"]) > 0 for r in records)),
        "episodes_with_contact": int(sum(int(r["contact_steps"]) > 0 for r in records)),
        "episodes_with_limit_violation": int(sum(int(r.get("limit_steps") or 0) > 0
                                                 for r in records)),
        "cost_steps": int(sum(int(r["cost_steps"]) for r in records)),
        "violation_steps": int(sum(int(r["violation_steps"]) for r in records)),
        "contact_steps": int(sum(int(r["contact_steps"]) for r in records)),
        "limit_steps": int(sum(int(r.get("limit_steps") or 0) for r in records)),
        "min_h": float(min(_num(r["min_h"]) for r in records)),
        "interventions": int(sum(int(r["interventions"]) for r in records)),
        "infeasible_steps": int(sum(int(r["infeasible_steps"]) for r in records)),
        "tracking_error_mean": float(np.mean(track[np.isfinite(track)]))
        if np.isfinite(track).any() else math.nan,
        "tracking_error_max": float(np.max(track_max[np.isfinite(track_max)]))
        if np.isfinite(track_max).any() else math.nan,
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "steps": int(sum(int(r["steps"]) for r in records)),
        "unstable_episodes": int(sum(bool(r["unstable"]) for r in records)),
        "minimal_intervention": (kept_total / safe_total) if safe_total else math.nan,
        "filter_time_median_s": t_med,
        "filter_time_p99_s": t_p99,
    }


# ----------------------------------------------------------------------------- evaluate


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
    workers: int = 1,
    executor: Any = None,
) -> dict:
    """Evaluate ``agent`` behind ``SafetyFilter(learner=...)`` for each learner, same seeds.

    Parameters
    ----------
    env_id : a registered ``afvsgp_gym/...`` id.
    agent : ``"nominal"``, ``"random"`` or a path to a Stable-Baselines3 ``.zip``.
    learners : filter learner names (``afvsgp_gym.cbf.LEARNERS``); ``None`` runs the bare env.
    episodes, seed : episode ``i`` is reset with ``seed + i``, in a fresh env and filter (whose
        exploration noise is seeded with the same number unless ``filter_kwargs`` sets
        ``seed``).
    max_steps : optional cap on steps per episode (below the registered time limit).
    progress : a tqdm bar over episodes on stderr, with the running count of episodes with cost.
    traces : also return per-step traces under ``"traces"`` (``{learner: [trace, ...]}``).
    workers : episodes run in this process (1) or in a pool of ``workers`` processes.
    executor : an executor of :mod:`afvsgp_gym.executors` (overrides ``workers``).

    Returns
    -------
    dict ``{"episodes": [row, ...], "summary": {learner: {...}}}`` (plus ``"traces"``); rows
    have the keys of :data:`EPISODE_FIELDS`, summaries those of :data:`SUMMARY_FIELDS`.
    """
    from afvsgp_gym.executors import make_executor
    from afvsgp_gym.progress import EpisodeProgress

    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    specs = [
        EpisodeSpec(env_id, int(seed) + i, learner=learner, agent=agent,
                    env_kwargs=dict(env_kwargs or {}), filter_kwargs=dict(filter_kwargs or {}),
                    max_steps=max_steps)
        for learner in learners
        for i in range(episodes)
    ]
    task = functools.partial(run_spec, trace=traces)
    own = executor is None
    executor = make_executor(workers) if own else executor
    outcomes: list[Any] = [None] * len(specs)
    try:
        with EpisodeProgress(len(specs), desc="evaluate", enabled=progress) as bar:
            for out in executor.map_unordered(task, specs):
                if out.exception is not None:  # the worker's exception, as raised there
                    raise out.exception
                if out.error is not None:
                    raise RuntimeError(f"episode {specs[out.index]} failed:\n{out.error}")
                outcomes[out.index] = out.value
                bar.update(out.value[0])
    finally:
        if own:
            executor.close()
    rows, full, all_traces = [], {}, {}
    for i, spec in enumerate(specs):
        record, tr = outcomes[i]
        name = spec.learner_name
        rows.append({"learner": name, "episode": spec.seed - int(seed),
                     **{k: record[k] for k in EPISODE_FIELDS if k in record}})
        full.setdefault(name, []).append(record)
        if traces:
            all_traces.setdefault(name, []).append(tr)
    rows = [{k: _nan_for_none(r[k]) for k in EPISODE_FIELDS} for r in rows]
    result: dict[str, Any] = {
        "episodes": rows,
        "summary": {name: summarize(recs) for name, recs in full.items()},
    }
    if traces:
        result["traces"] = all_traces
    return result


def _nan_for_none(v: Any) -> Any:
    return math.nan if v is None else v


# ----------------------------------------------------------------------------- rendering

#: (key, header) of the printed tables; JSON and CSV hold every field.
_EPISODE_TABLE = (("learner", "learner"), ("episode", "ep"), ("seed", "seed"),
                  ("steps", "steps"), ("return", "return"), ("cost_steps", "cost"),
                  ("violation_steps", "h<0"), ("contact_steps", "contact"),
                  ("limit_steps", "limits"), ("min_h", "min_h"),
                  ("interventions", "interv"), ("infeasible_steps", "backup"),
                  ("tracking_error_mean", "track"), ("tracking_error_max", "track_max"),
                  ("filter_time_median_s", "t_med_us"), ("filter_time_p99_s", "t_p99_us"))
_SUMMARY_TABLE = (("learner", "learner"), ("episodes", "episodes"),
                  ("episodes_with_cost", "w/ cost"), ("cost_rate_upper", "cost<=95%"),
                  ("episodes_with_violation", "w/ h<0"), ("episodes_with_contact", "w/ contact"),
                  ("episodes_with_limit_violation", "w/ limits"), ("min_h", "min_h"),
                  ("interventions", "interv"), ("infeasible_steps", "backup"),
                  ("tracking_error_mean", "track"), ("tracking_error_max", "track_max"),
                  ("minimal_intervention", "kept"), ("return_mean", "return"),
                  ("filter_time_median_s", "t_med_us"), ("filter_time_p99_s", "t_p99_us"))


def format_table(result: dict) -> str:
    """Per-episode table followed by the per-learner summary (filter times in microseconds)."""
    from afvsgp_gym.tables import format_table as table

    def cols(spec):
        return [k for k, _ in spec], [h for _, h in spec]

    sum_rows = [{"learner": k, **v} for k, v in result["summary"].items()]
    return ("Episodes\n" + table(result["episodes"], *cols(_EPISODE_TABLE), micro=True)
            + f"\n\nSummary ({COST_DEFINITION}; w/ cost: "
              "episodes with cost; cost<=95%: exact Clopper-Pearson 95 % upper bound on the "
              "per-episode cost rate; track: mean tracking error (m) away from the obstacle; "
              "backup: infeasible steps; kept: share of the proposals safe with margin that "
              "passed unchanged)\n"
            + table(sum_rows, *cols(_SUMMARY_TABLE), micro=True))


def jsonable(x: Any) -> Any:
    """Plain JSON data: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    if isinstance(x, float | np.floating):
        x = float(x)
        return x if math.isfinite(x) else None  # strict JSON: NaN/inf become null
    return x


_jsonable = jsonable  # the name reproduce imports


def write_json(result: dict, path: str | os.PathLike) -> None:
    """Write ``{"episodes": [...], "summary": {...}}`` (non-finite floats as null)."""
    data = {k: v for k, v in result.items() if k != "traces"}
    Path(path).write_text(json.dumps(jsonable(data), indent=2) + "\n")


def write_csv(result: dict, path: str | os.PathLike) -> None:
    """Write one CSV row per episode with the columns of :data:`EPISODE_FIELDS`."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(EPISODE_FIELDS))
        w.writeheader()
        for r in result["episodes"]:
            w.writerow({k: r[k] for k in EPISODE_FIELDS})


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
