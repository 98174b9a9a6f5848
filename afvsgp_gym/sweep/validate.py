"""Check a parsed sweep against the envs, learners, filter and agents before anything runs.

Every env id must be registered, every learner in ``afvsgp_gym.cbf.LEARNERS`` (or
``"unfiltered"``), every agent a built-in one or an existing Stable-Baselines3 zip that fits the
env, every filter kwarg a keyword of :class:`~afvsgp_gym.cbf.SafetyController` (or the wrapper's
``backup``; the episode seed seeds the filter, so ``seed`` is refused). Values are checked by
constructing: each env id once with the first alternative of every env kwarg and once more per
other alternative (one axis changed at a time, so the cost grows with the sum of the axis
lengths, not their product), and a :class:`~afvsgp_gym.wrappers.SafetyFilter` the same way for
the filter kwargs. Errors are :class:`~afvsgp_gym.sweep.config.ConfigError` naming the grid,
the key and the value.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from afvsgp_gym.sweep.config import UNFILTERED, Block, ConfigError, Sweep

__all__ = ["filter_kwarg_names", "validate"]

#: SafetyController arguments the wrapper or the sweep sets itself.
_RESERVED = {
    "self": "",
    "action_low": "set from the env's action space",
    "action_high": "set from the env's action space",
    "n_obstacles": "set from the env",
    "n_barriers": "set from the env",
    "relative_degree": "set from the env",
    "learner": "use the grid's 'learners'",
    "seed": "each episode seeds the filter with its own seed",
}


def filter_kwarg_names() -> tuple[str, ...]:
    """Keyword options a grid may sweep in ``filter_kwargs``: the wrapper's own (``backup``,
    ``oracle_terms``, ``obstacle_estimator``, ...), the controller's ``dataset`` and the
    fields of :class:`~afvsgp_gym.cbf.FilterConfig`."""
    from afvsgp_gym.cbf import FilterConfig, SafetyController
    from afvsgp_gym.wrappers import SafetyFilter

    wrapper = [n for n, p in inspect.signature(SafetyFilter.__init__).parameters.items()
               if n not in ("self", "env", "learner") and p.kind == p.POSITIONAL_OR_KEYWORD]

    params = inspect.signature(SafetyController.__init__).parameters
    names = [n for n, p in params.items()
             if n not in _RESERVED and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    names += [n for n in FilterConfig.option_names() if n not in _RESERVED]
    return (*wrapper, *names)


def _one_axis_at_a_time(axes: Mapping[str, list]) -> list[dict[str, Any]]:
    """The first alternative of every axis, then each other alternative with the rest first."""
    base = {k: v[0] for k, v in axes.items()}
    out = [base]
    for k, alts in axes.items():
        out += [{**base, k: a} for a in alts[1:]]
    return out


def _checked(where: str, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)``, any exception turned into a ConfigError naming ``what``."""
    try:
        return fn(*args, **kwargs)
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(f"{where}: {what}: {type(exc).__name__}: {exc}") from None


def _check_names(where: str, block: Block) -> None:
    import gymnasium as gym

    import afvsgp_gym  # noqa: F401  (registers the ids)
    from afvsgp_gym.cbf import LEARNERS
    from afvsgp_gym.evaluation import BUILTIN_AGENTS

    ids = sorted(k for k in gym.registry if k.startswith("afvsgp_gym/"))
    for env in block.envs:
        if env not in gym.registry:
            raise ConfigError(f"{where}: unknown env id {env!r}; valid: {', '.join(ids)}")
    for learner in block.learners:
        if learner is not None and learner not in LEARNERS:
            raise ConfigError(f"{where}: unknown learner {learner!r}; valid: "
                              f"{', '.join(LEARNERS)}, {UNFILTERED}")
    for agent in block.agents:
        if agent in BUILTIN_AGENTS:
            continue
        if not agent.endswith(".zip"):
            raise ConfigError(f"{where}: unknown agent {agent!r}; valid: "
                              f"{', '.join(BUILTIN_AGENTS)} or a path to a Stable-Baselines3 "
                              ".zip")
        if not Path(agent).is_file():
            raise ConfigError(f"{where}: agent zip {agent!r} does not exist")
    valid = filter_kwarg_names()
    for name in block.filter_kwargs:
        if name in _RESERVED:
            raise ConfigError(f"{where}: filter_kwargs.{name} cannot be swept: "
                              f"{_RESERVED[name]}")
        if name not in valid:
            raise ConfigError(f"{where}: unknown filter kwarg {name!r}; valid: "
                              f"{', '.join(valid)}")
    if block.filter_kwargs and all(x is None for x in block.learners):
        raise ConfigError(f"{where}: filter_kwargs given but every learner is {UNFILTERED!r}")


def _check_values(where: str, block: Block, made: dict[str, Any], built: set[str]) -> None:
    """Make every env of ``block`` (one kwargs axis at a time) and build the filter of every
    learner and filter-kwargs alternative on the first. ``made`` (envs by their kwargs) and
    ``built`` (filters checked) carry over between blocks: an entry already checked is not
    checked again."""
    import gymnasium as gym

    from afvsgp_gym.wrappers import SafetyFilter

    learners = [x for x in block.learners if x is not None]
    for env_id in block.envs:
        keys = []
        for kw in _one_axis_at_a_time(block.env_kwargs):
            key = json.dumps([env_id, kw], sort_keys=True, default=repr)
            if key not in made:
                made[key] = _checked(where, f"env {env_id} with env_kwargs {kw}", gym.make,
                                     env_id, **kw)
            keys.append(key)
        first = made[keys[0]]
        for learner in learners:
            for fkw in _one_axis_at_a_time(block.filter_kwargs):
                key = json.dumps([keys[0], learner, fkw], sort_keys=True, default=repr)
                if key not in built:
                    _checked(where, f"learner {learner!r} with filter_kwargs {fkw} on {env_id}",
                             SafetyFilter, first, learner=learner, seed=0, **fkw)
                    built.add(key)
        for agent in block.agents:
            if agent.endswith(".zip"):
                from afvsgp_gym.agents.sb3 import load_policy

                _checked(where, f"agent {agent!r} on {env_id}", load_policy, agent, env=first)


def validate(sweep: Sweep) -> None:
    """Raise :class:`ConfigError` at the first entry of ``sweep`` that cannot run."""
    made: dict[str, Any] = {}
    built: set[str] = set()
    try:
        for i, block in enumerate(sweep.blocks):
            where = f"grid[{i}] {block.name!r}"
            _check_names(where, block)
            _check_values(where, block, made, built)
    finally:
        for env in made.values():
            env.close()
