"""Sweep configuration: a file of grids, expanded into episode specs.

A CONFIG (TOML, JSON, or YAML when PyYAML is installed) holds an optional ``description``, an
optional ``[defaults]`` table and one or more ``[[grid]]`` blocks; each block is the product
``envs x env_kwargs x learners x filter_kwargs x agents x seeds`` and the sweep is the union of
its blocks (an episode in two blocks runs once)::

    [defaults]
    agents = ["nominal"]
    max_steps = 1000                      # optional cap below the env's time limit

    [[grid]]
    name = "priors"                       # optional label, kept in the records
    envs = ["afvsgp_gym/FrankaObstacleStatic-v0", "afvsgp_gym/FrankaObstacleDynamic-v0"]
    learners = ["afvsgp"]                 # afvsgp_gym.cbf.LEARNERS or "unfiltered"
    seeds = {start = 0, count = 20}       # or a list: [0, 1, 2]
    [grid.env_kwargs]                     # every value is a list of alternatives
    nominal_model = ["zero", "kinematic", "perturbed"]
    mass_scale = [[0.9, 1.3]]             # a list-valued argument is wrapped in a list
    [grid.filter_kwargs]
    beta = [3.0]

A block's keys override ``defaults``; its ``env_kwargs``/``filter_kwargs`` axes are merged
with those of ``defaults``. :func:`load_config` reads and checks the structure (unknown keys
and wrong types are refused, naming them); :mod:`afvsgp_gym.sweep.validate` checks the
values against the envs, learners and agents before anything runs.
"""

from __future__ import annotations

import itertools
import json
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from afvsgp_gym.evaluation import UNFILTERED, EpisodeSpec

__all__ = ["BLOCK_KEYS", "Block", "ConfigError", "Sweep", "load_config", "parse_config"]

TOP_KEYS = ("description", "defaults", "grid")
BLOCK_KEYS = ("name", "envs", "env_kwargs", "learners", "filter_kwargs", "agents", "seeds",
              "max_steps")


class ConfigError(ValueError):
    """A sweep configuration that cannot run; the message names the offending entry."""


@dataclass(frozen=True)
class Block:
    """One grid: the product of its axes (kwargs axes map a name to its alternatives)."""

    name: str
    envs: tuple[str, ...]
    env_kwargs: dict[str, list]
    learners: tuple[str | None, ...]
    filter_kwargs: dict[str, list]
    agents: tuple[str, ...]
    seeds: tuple[int, ...]
    max_steps: int | None

    def specs(self) -> list[EpisodeSpec]:
        """Every episode of the block, seed by seed (each seed runs every configuration before
        the next seed starts, so any prefix of a sweep covers the configurations evenly)."""
        return [
            EpisodeSpec(env, seed, learner=learner, agent=agent, env_kwargs=ekw,
                        filter_kwargs=fkw, max_steps=self.max_steps)
            for seed in self.seeds
            for env in self.envs
            for ekw in combinations(self.env_kwargs)
            for learner in self.learners
            for fkw in combinations(self.filter_kwargs)
            for agent in self.agents
        ]


@dataclass(frozen=True)
class Sweep:
    """A parsed configuration: its blocks and the deduplicated episodes with their block."""

    blocks: tuple[Block, ...]
    description: str = ""

    def episodes(self) -> list[tuple[str, EpisodeSpec]]:
        """``(block name, spec)`` per distinct episode (first block wins), in config order."""
        seen: set[str] = set()
        out = []
        for block in self.blocks:
            for spec in block.specs():
                key = spec.key()
                if key not in seen:
                    seen.add(key)
                    out.append((block.name, spec))
        return out

    def size(self) -> int:
        """Episodes counted with repetitions across blocks."""
        return sum(len(b.specs()) for b in self.blocks)


def combinations(axes: Mapping[str, list]) -> list[dict[str, Any]]:
    """The product of kwargs axes: ``{"a": [1, 2]}`` -> ``[{"a": 1}, {"a": 2}]``."""
    names = list(axes)
    return [dict(zip(names, values, strict=True))
            for values in itertools.product(*(axes[n] for n in names))]


def _read(path: Path) -> Any:
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            if sys.version_info >= (3, 11):
                import tomllib
            else:  # pragma: no cover - Python 3.10
                import tomli as tomllib
            with open(path, "rb") as fh:
                return tomllib.load(fh)
        if suffix == ".json":
            return json.loads(path.read_text())
        if suffix in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError:
                raise ConfigError(f"{path}: YAML configs need PyYAML (pip install pyyaml); "
                                  "or write the config as TOML or JSON") from None
            return yaml.safe_load(path.read_text())
    except ConfigError:
        raise
    except OSError as exc:
        raise ConfigError(f"cannot read config {str(path)!r}: {exc}") from None
    except Exception as exc:  # a syntax error of the format
        raise ConfigError(f"{path}: not valid {suffix[1:].upper()}: {exc}") from None
    raise ConfigError(f"config {str(path)!r}: unknown format {suffix!r}; use .toml, .json, "
                      ".yaml or .yml")


def load_config(path: str | Path) -> Sweep:
    """Read and parse a CONFIG file (see the module docstring); raises :class:`ConfigError`."""
    path = Path(path)
    return parse_config(_read(path), source=str(path))


def _unknown(where: str, keys, valid) -> None:
    bad = [k for k in keys if k not in valid]
    if bad:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, bad))}; valid keys: "
                          f"{', '.join(valid)}")


def parse_config(data: Any, source: str = "CONFIG") -> Sweep:
    """Check the structure of a loaded CONFIG and build the :class:`Sweep`."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a table/object at the top, got "
                          f"{type(data).__name__}")
    _unknown(source, data, TOP_KEYS)
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"{source}: description must be a string")
    defaults = data.get("defaults", {})
    if not isinstance(defaults, Mapping):
        raise ConfigError(f"{source}: defaults must be a table of block keys")
    _unknown(f"{source}: defaults", defaults, BLOCK_KEYS)
    if "name" in defaults:
        raise ConfigError(f"{source}: defaults cannot set 'name' (each grid has its own)")
    grid = data.get("grid")
    if isinstance(grid, Mapping):
        grid = [grid]
    if not isinstance(grid, list) or not grid:
        raise ConfigError(f"{source}: needs at least one [[grid]] block (a list of tables)")
    blocks, names = [], set()
    for i, raw in enumerate(grid):
        where = f"{source}: grid[{i}]"
        if not isinstance(raw, Mapping):
            raise ConfigError(f"{where}: expected a table, got {type(raw).__name__}")
        _unknown(where, raw, BLOCK_KEYS)
        block = _block(i, {**defaults, **raw, **_merged_axes(defaults, raw)}, where)
        if block.name in names:
            raise ConfigError(f"{where}: duplicate grid name {block.name!r}")
        names.add(block.name)
        blocks.append(block)
    return Sweep(tuple(blocks), description)


def _merged_axes(defaults: Mapping, raw: Mapping) -> dict:
    out = {}
    for key in ("env_kwargs", "filter_kwargs"):
        d, r = defaults.get(key, {}), raw.get(key, {})
        if isinstance(d, Mapping) and isinstance(r, Mapping):
            out[key] = {**d, **r}
    return out


def _strings(where: str, key: str, v: Any) -> tuple[str, ...]:
    if not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v):
        raise ConfigError(f"{where}: {key} must be a non-empty list of strings, got {v!r}")
    return tuple(v)


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _seeds(where: str, v: Any) -> tuple[int, ...]:
    if isinstance(v, Mapping):
        _unknown(f"{where}: seeds", v, ("start", "count"))
        start, count = v.get("start", 0), v.get("count")
        if not (_int(start) and _int(count) and count >= 1):
            raise ConfigError(f"{where}: seeds = {{start, count}} needs integers with count >= 1,"
                              f" got {dict(v)!r}")
        return tuple(range(start, start + count))
    if isinstance(v, list) and v and all(_int(x) for x in v):
        if len(set(v)) != len(v):
            raise ConfigError(f"{where}: seeds has repeated values: {v!r}")
        return tuple(v)
    raise ConfigError(f"{where}: seeds must be a non-empty list of integers or "
                      f"{{start = S, count = N}}, got {v!r}")


def _axes(where: str, key: str, v: Any) -> dict[str, list]:
    if not isinstance(v, Mapping):
        raise ConfigError(f"{where}: {key} must be a table of name = [alternatives, ...], "
                          f"got {v!r}")
    for name, alts in v.items():
        if not isinstance(alts, list) or not alts:
            raise ConfigError(
                f"{where}: {key}.{name} must be a non-empty list of the values to sweep (wrap "
                f"a single value, and a list-valued argument, in a list: [{json.dumps(alts)}])")
    return {str(k): list(alts) for k, alts in v.items()}


def _block(i: int, raw: Mapping, where: str) -> Block:
    for key in ("envs", "learners", "seeds"):
        if key not in raw:
            raise ConfigError(f"{where}: missing required key {key!r}")
    name = raw.get("name", f"grid{i}")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: name must be a non-empty string, got {name!r}")
    max_steps = raw.get("max_steps")
    if max_steps is not None and not (_int(max_steps) and max_steps >= 1):
        raise ConfigError(f"{where}: max_steps must be a positive integer, got {max_steps!r}")
    learners = _strings(where, "learners", raw["learners"])
    return Block(
        name=name,
        envs=_strings(where, "envs", raw["envs"]),
        env_kwargs=_axes(where, "env_kwargs", raw.get("env_kwargs", {})),
        learners=tuple(None if x == UNFILTERED else x for x in learners),
        filter_kwargs=_axes(where, "filter_kwargs", raw.get("filter_kwargs", {})),
        agents=_strings(where, "agents", raw.get("agents", ["nominal"])),
        seeds=_seeds(where, raw["seeds"]),
        max_steps=max_steps,
    )
