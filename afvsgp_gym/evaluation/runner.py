"""The one episode runner: :func:`run_episode` counts an episode, :func:`run_spec` runs the
episode of an :class:`~afvsgp_gym.evaluation.EpisodeSpec` in a fresh env and filter,
:func:`evaluate` runs the specs of an evaluation through an executor and summarizes them."""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from afvsgp_gym.episode_counts import CALIBRATION_FIELDS, EpisodeCounter
from afvsgp_gym.evaluation.factories import Policy, make_env, make_policy
from afvsgp_gym.evaluation.io import jsonable
from afvsgp_gym.evaluation.spec import EpisodeSpec
from afvsgp_gym.evaluation.summary import summarize
from afvsgp_gym.evaluation.version import code_version, cpu_model

__all__ = ["COUNT_FIELDS", "EPISODE_FIELDS", "REFERENCE_CLEARANCE", "evaluate", "run_episode",
           "run_spec"]

#: Counted columns of one episode (records of :func:`run_spec` hold them all).
COUNT_FIELDS = (
    "steps",
    "return",
    "cost_steps",
    "violation_steps",
    "contact_steps",
    "self_contact_steps",
    "limit_steps",
    "min_h",
    "interventions",
    "infeasible_steps",
    "learner_error_steps",
    *CALIBRATION_FIELDS,
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

#: m; tracking error counts where the reference's ee sphere keeps this clearance (reference_h).
REFERENCE_CLEARANCE = 0.05


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

    ``counts`` has the keys of :data:`COUNT_FIELDS` (counted by
    :class:`~afvsgp_gym.episode_counts.EpisodeCounter`, tracking error here) plus
    ``"filter_time_hist"`` (the step times as a :func:`afvsgp_gym.stats.time_histogram`).
    ``trace`` (when asked) holds per-step arrays ``t``, ``h``, ``delta_b_true``,
    ``delta_b_mean``, ``delta_b_std`` (first barrier), ``filter_active``. ``on_step(info)``
    (optional) is called after every step.
    """
    from afvsgp_gym.stats import time_histogram

    obs, info = env.reset(seed=int(seed))
    base = env.unwrapped
    dt = float(getattr(base, "dt", 1.0))
    warmup_steps = int(getattr(base, "warmup_steps", 0) or 0)
    counter = EpisodeCounter()
    track: list[float] = []
    tr: dict[str, list] = {k: [] for k in ("h", "delta_b_true", "delta_b_mean", "delta_b_std",
                                           "filter_active")}
    while True:
        action = policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        counter.update(reward, info)
        steps = counter.steps
        err, ref_h = _tracking(base, info)
        if steps > warmup_steps and ref_h >= REFERENCE_CLEARANCE and math.isfinite(err):
            track.append(err)
        if trace:
            tr["h"].append(float(info.get("h", math.nan)))
            for k in ("delta_b_true", "delta_b_mean", "delta_b_std"):
                tr[k].append(_first(info.get(k)))
            tr["filter_active"].append(bool(info.get("filter_active", False)))
        if on_step is not None:
            on_step(info)
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            break
    times = counter.filter_times
    counts = {
        "steps": counter.steps,
        "return": counter.return_,
        "cost_steps": counter.cost_steps,
        "violation_steps": counter.violation_steps,
        "contact_steps": counter.contact_steps,
        "self_contact_steps": counter.self_contact_steps,
        "limit_steps": counter.limit_steps,
        "min_h": counter.min_h,
        "interventions": counter.interventions,
        "infeasible_steps": counter.infeasible_steps,
        "learner_error_steps": counter.learner_error_steps,
        **{name: getattr(counter, name) for name in CALIBRATION_FIELDS},
        "tracking_error_mean": float(np.mean(track)) if track else math.nan,
        "tracking_error_max": float(np.max(track)) if track else math.nan,
        "unstable": counter.unstable,
        "safe_proposals": counter.safe_proposals,
        "safe_proposals_kept": counter.safe_proposals_kept,
        "filter_time_median_s": float(np.median(times)) if times else math.nan,
        "filter_time_p99_s": float(np.percentile(times, 99)) if times else math.nan,
        "filter_time_hist": time_histogram(times),
    }
    trace_out = None
    if trace:
        trace_out = {k: np.asarray(v, dtype=float) for k, v in tr.items()}
        trace_out["t"] = dt * np.arange(1, counter.steps + 1)
    return counts, trace_out


def _first(x: Any) -> float:
    """First entry of a per-barrier array (or a scalar); NaN when absent."""
    if x is None:
        return math.nan
    a = np.ravel(np.asarray(x, dtype=float))
    return float(a[0]) if a.size else math.nan


def run_spec(spec: EpisodeSpec, trace: bool = False) -> tuple[dict, dict | None]:
    """Run one episode in a fresh env and filter; returns ``(record, trace)``.

    The record (JSON-able) holds ``key``, ``config``, ``seed``, ``code_version``,
    ``brake_version`` and ``cost_version`` (the env's ``BRAKE_VERSION`` and
    ``COST_VERSION``, where it declares them: the Franka envs), ``self_collision`` (whether
    the env's self-collision barriers were on, where it has them),
    ``learner_used`` (the filter's learner, the env's suggestion for ``"auto"``), the counts
    of :func:`run_episode`, ``wall_s`` and ``cpu_s`` (construction and run, wall-clock and
    CPU time of the worker), ``host``, ``machine`` (the CPU model) and ``date`` (the day it
    ran).
    This is the task every executor runs.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    env = make_env(spec)
    base = env.unwrapped
    brake = getattr(base, "BRAKE_VERSION", None)
    cost_version = getattr(base, "COST_VERSION", None)
    self_collision = getattr(base, "self_collision", None)
    used = getattr(env, "learner_name", None)  # the filter's learner ("auto" resolved)
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
        **({} if brake is None else {"brake_version": int(brake)}),
        **({} if cost_version is None else {"cost_version": int(cost_version)}),
        **({} if self_collision is None else {"self_collision": bool(self_collision)}),
        **({} if used is None else {"learner_used": str(used)}),
        **counts,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "host": os.uname().nodename if hasattr(os, "uname") else "",
        "machine": cpu_model(),
        "date": time.strftime("%Y-%m-%d"),
    }
    return jsonable(record), tr


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
    learners : filter learner names (``afvsgp_gym.cbf.LEARNERS``, or ``"auto"``: the env's
        suggestion, labelled ``"auto (<learner>)"`` in the result); ``None`` runs the bare env.
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
        if name == "auto" and record.get("learner_used"):  # which learner the env suggested
            name = f"auto ({record['learner_used']})"
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
