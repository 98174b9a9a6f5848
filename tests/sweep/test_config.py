"""CONFIG files: grids expand to the expected episodes; bad input is refused before anything
runs, naming the entry."""

import json
import sys

import pytest

from afvsgp_gym.cli import main
from afvsgp_gym.sweep import ConfigError, load_config, parse_config, validate
from afvsgp_gym.sweep.validate import filter_kwarg_names

PM = "afvsgp_gym/PointMassObstacle-v0"
FR = "afvsgp_gym/FrankaObstacleStatic-v0"

TOML = f"""
description = "two grids"
[defaults]
max_steps = 50
agents = ["nominal"]
[defaults.env_kwargs]
scenario = ["static"]

[[grid]]
name = "a"
envs = ["{PM}"]
learners = ["afvsgp", "none"]
seeds = {{start = 3, count = 2}}
[grid.env_kwargs]
scenario = ["static", "dynamic"]
obstacle_speed = [0.1, 0.2]
[grid.filter_kwargs]
beta = [1.0, 3.0]

[[grid]]
name = "b"
envs = ["{PM}"]
learners = ["none", "unfiltered"]
agents = ["random"]
seeds = [3]
max_steps = 20
"""


def test_toml_grid_expands_as_the_product(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(TOML)
    sweep = load_config(path)
    a, b = sweep.blocks
    assert a.max_steps == 50 and b.max_steps == 20  # block overrides defaults
    assert b.env_kwargs == {"scenario": ["static"]}  # axes merged from defaults
    specs = a.specs()
    assert len(specs) == 2 * 2 * 2 * 2 * 2  # scenario x speed x learner x beta x seeds
    assert {s.seed for s in specs} == {3, 4}
    assert {(s.env_kwargs["scenario"], s.env_kwargs["obstacle_speed"], s.learner,
             s.filter_kwargs["beta"], s.seed) for s in specs} == {
        (sc, sp, lr, be, sd) for sc in ("static", "dynamic") for sp in (0.1, 0.2)
        for lr in ("afvsgp", "none") for be in (1.0, 3.0) for sd in (3, 4)}
    assert [s.learner for s in b.specs()] == ["none", None]
    assert len(sweep.episodes()) == 32 + 2
    validate(sweep)  # every entry is runnable


def test_json_config_and_repeated_episodes_run_once(tmp_path):
    block = {"envs": [PM], "learners": ["none"], "seeds": [0, 1]}
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"grid": [{"name": "x", **block},
                                         {"name": "y", **block, "seeds": [1, 2]}]}))
    sweep = load_config(path)
    assert sweep.size() == 4
    assert [(blk, s.seed) for blk, s in sweep.episodes()] == [("x", 0), ("x", 1), ("y", 2)]


def test_yaml_needs_pyyaml_or_works(tmp_path, monkeypatch):
    path = tmp_path / "c.yaml"
    path.write_text(f"grid:\n  - envs: [{PM}]\n    learners: [none]\n    seeds: [0]\n")
    try:
        import yaml  # noqa: F401
    except ImportError:
        pass
    else:
        assert len(load_config(path).episodes()) == 1
    monkeypatch.setitem(sys.modules, "yaml", None)  # as if PyYAML were absent
    with pytest.raises(ConfigError, match="pip install pyyaml"):
        load_config(path)


BASE = {"envs": [PM], "learners": ["none"], "seeds": [0]}


@pytest.mark.parametrize("data, message", [
    ({"grid": [BASE], "grids": []}, "unknown key(s) 'grids'"),
    ({"grid": [{**BASE, "seed": [1]}]}, "unknown key(s) 'seed'"),
    ({"defaults": {"learner": ["x"]}, "grid": [BASE]}, "defaults: unknown key(s) 'learner'"),
    ({"grid": []}, "at least one [[grid]]"),
    ({"grid": [{"envs": [PM], "seeds": [0]}]}, "missing required key 'learners'"),
    ({"grid": [{**BASE, "seeds": [0, 0]}]}, "repeated"),
    ({"grid": [{**BASE, "seeds": {"start": 0}}]}, "count >= 1"),
    ({"grid": [{**BASE, "seeds": {"begin": 0, "count": 2}}]}, "unknown key(s) 'begin'"),
    ({"grid": [{**BASE, "env_kwargs": {"scenario": "static"}}]},
     "env_kwargs.scenario must be a non-empty list"),
    ({"grid": [{**BASE, "learners": "none"}]}, "learners must be a non-empty list"),
    ({"grid": [{**BASE, "max_steps": 0}]}, "max_steps must be a positive integer"),
    ({"grid": [{**BASE, "name": "a"}, {**BASE, "name": "a"}]}, "duplicate grid name 'a'"),
])
def test_structure_errors_name_the_entry(data, message):
    with pytest.raises(ConfigError) as exc:
        parse_config(data)
    assert message in str(exc.value)


@pytest.mark.parametrize("block, message", [
    ({"envs": ["afvsgp_gym/Nope-v0"]}, "unknown env id 'afvsgp_gym/Nope-v0'"),
    ({"learners": ["magic"]}, "unknown learner 'magic'"),
    ({"agents": ["genius"]}, "unknown agent 'genius'"),
    ({"agents": ["missing.zip"]}, "agent zip 'missing.zip' does not exist"),
    ({"env_kwargs": {"payload": [1.0]}}, "unknown argument(s) ['payload']"),
    ({"env_kwargs": {"scenario": ["static", "wobbly"]}}, "wobbly"),
    ({"filter_kwargs": {"betta": [1.0]}}, "unknown filter kwarg 'betta'"),
    ({"filter_kwargs": {"seed": [1]}}, "filter_kwargs.seed cannot be swept"),
    ({"filter_kwargs": {"beta": [1.0, -2.0]}}, "beta"),
    ({"learners": ["unfiltered"], "filter_kwargs": {"beta": [1.0]}}, "every learner is"),
])
def test_value_errors_name_the_entry(block, message):
    sweep = parse_config({"grid": [{**BASE, "name": "g", **block}]})
    with pytest.raises(ConfigError) as exc:
        validate(sweep)
    assert message in str(exc.value) and "'g'" in str(exc.value)


def test_franka_kwargs_are_checked_by_construction():
    sweep = parse_config({"grid": [{"envs": [FR], "learners": ["afvsgp"], "seeds": [0],
                                    "env_kwargs": {"nominal_model": ["zero", "exact", "guess"],
                                                   "payload_mass": [1.0, 2.0]}}]})
    with pytest.raises(ConfigError, match="nominal_model.*guess"):
        validate(sweep)


def test_filter_kwarg_names_follow_the_controller():
    names = filter_kwarg_names()
    assert "backup" in names and "beta" in names and "alpha" in names
    assert "seed" not in names and "learner" not in names


def test_cli_refuses_before_running(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(TOML.replace('learners = ["afvsgp", "none"]', 'learners = ["afvsgp", "x"]'))
    out = tmp_path / "r.jsonl"
    with pytest.raises(SystemExit) as exc:
        main(["sweep", str(cfg), "--out", str(out), "--no-progress"])
    assert exc.value.code == 2
    assert "unknown learner 'x'" in capsys.readouterr().err
    assert not out.exists()  # nothing ran, nothing written
    with pytest.raises(SystemExit) as exc:
        main(["sweep", str(tmp_path / "nope.toml"), "--out", str(out)])
    assert exc.value.code == 2
    assert "cannot read config" in capsys.readouterr().err
    cfg.write_text("grid = [")
    with pytest.raises(SystemExit) as exc:
        main(["sweep", str(cfg), "--out", str(out)])
    assert exc.value.code == 2
    assert "not valid TOML" in capsys.readouterr().err


def test_dry_run_counts(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(TOML)
    assert main(["sweep", str(cfg), "--dry-run", "--out", str(tmp_path / "r.jsonl")]) == 0
    out = capsys.readouterr().out
    assert "34 episodes in 2 grid(s)" in out and "a: 32 episodes" in out
    assert not (tmp_path / "r.jsonl").exists()


def _configs_dir():
    """benchmarks/configs of the source tree."""
    from pathlib import Path

    import afvsgp_gym

    return Path(afvsgp_gym.__file__).resolve().parent.parent / "benchmarks" / "configs"


def test_shipped_acceptance_config_is_valid_and_large_enough():
    sweep = load_config(_configs_dir() / "acceptance.toml")
    validate(sweep)
    episodes = [s for _, s in sweep.episodes()]
    afvsgp = [s for s in episodes if s.learner == "afvsgp"
              and s.env_id.startswith("afvsgp_gym/Franka")
              and s.env_kwargs.get("safety_spheres", "arm") == "arm"]  # whole-arm Franka
    assert len(afvsgp) >= 1000
    assert {s.env_id for s in afvsgp} == {f"afvsgp_gym/FrankaObstacle{k}-v0"
                                          for k in ("Static", "Dynamic", "Random")}
    assert {s.env_kwargs["nominal_model"] for s in afvsgp} == {"zero", "kinematic", "perturbed"}
    for kwarg in ("plant_seed", "payload_mass", "friction", "obstacle_speed"):
        assert len({s.env_kwargs.get(kwarg) for s in afvsgp}) >= 2, kwarg
    assert {s.learner for s in episodes} == {"afvsgp", "oracle", "none"}


@pytest.mark.parametrize("path", sorted(_configs_dir().glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_benchmark_config_is_valid(path):
    """The configs that benchmarks/*.md tell users to run load, validate against the envs,
    learners and filter, and have at least one episode."""
    sweep = load_config(path)
    validate(sweep)
    assert sum(1 for _ in sweep.episodes()) > 0
