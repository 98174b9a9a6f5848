"""The class docstrings are the spec: every argument and its default appear in ## Arguments,
read from the explicit signature that help() shows."""

import ast
import inspect
import pydoc

import gymnasium as gym
import pytest

import afvsgp_gym  # noqa: F401  (registers the ids)
from afvsgp_gym.envs.base import UnknownArgumentError
from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.point_mass import PointMassObstacleEnv
from afvsgp_gym.envs.reach import FrankaObstacleReachEnv

ENVS = [PointMassObstacleEnv, FrankaObstacleEnv, FrankaObstacleReachEnv]


def _argument_rows(cls):
    doc = cls.__doc__
    section = doc.split("## Arguments", 1)[1].split("##", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0] not in ("Parameter", "---"):
            names = [n.strip() for n in cells[0].split(",")]
            values = [v.strip() for v in cells[1].split(", ")] if len(names) > 1 else [cells[1]]
            if len(values) == 1:  # one value for all the names of the row
                values *= len(names)
            for name, value in zip(names, values, strict=True):
                rows[name] = value
    return rows


def _value(cell):
    """A table cell as the Python value it writes (``"zero"``, ``None``, ``4e-4``, ...)."""
    return ast.literal_eval(cell)


def _signature_defaults(cls):
    return {name: p.default for name, p in inspect.signature(cls).parameters.items()}


@pytest.mark.parametrize("cls", [PointMassObstacleEnv, FrankaObstacleEnv])
def test_arguments_table_matches_the_signature(cls):
    rows = _argument_rows(cls)
    defaults = _signature_defaults(cls)
    assert set(rows) == set(defaults)
    for name, default in defaults.items():
        assert _value(rows[name]) == default, name


def test_reach_arguments_table_names_every_argument():
    """The reach task's table gives its own defaults and the plant's "as Franka" (the
    obstacle env's defaults, which its signature takes)."""
    rows = _argument_rows(FrankaObstacleReachEnv)
    defaults = _signature_defaults(FrankaObstacleReachEnv)
    assert set(rows) == set(defaults)
    for name, default in defaults.items():
        if rows[name] == "as Franka":
            assert default == FrankaObstacleEnv._DEFAULTS[name], name
        else:
            assert _value(rows[name]) == default, name


@pytest.mark.parametrize("cls", ENVS)
def test_signature_is_explicit_and_unknown_arguments_are_named(cls):
    """help() shows every argument (keyword-only after ``scenario``, no ``**kwargs``), and
    ``_DEFAULTS`` is read from it; an unknown keyword, also through gym.make, raises a
    TypeError (and ValueError) naming the valid ones."""
    params = inspect.signature(cls).parameters
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for n, p in params.items()
               if n != "scenario")
    assert cls._DEFAULTS == {n: p.default for n, p in params.items() if n != "scenario"}
    assert "nominal_model: 'str' = 'zero'" in pydoc.plain(pydoc.render_doc(cls))  # help()
    valid = list(params)
    with pytest.raises(UnknownArgumentError) as exc:
        cls(payload=1.0)
    assert str(exc.value) == f"unknown argument(s) ['payload']; valid: {valid}"
    assert isinstance(exc.value, TypeError) and isinstance(exc.value, ValueError)


def test_gym_make_passes_keywords_to_the_signature():
    env = gym.make("afvsgp_gym/PointMassObstacle-v0", dim=3, mass=2.0)
    assert (env.unwrapped.dim, env.unwrapped.mass) == (3, 2.0)
    with pytest.raises(UnknownArgumentError, match=r"unknown argument\(s\) \['masss'\]"):
        gym.make("afvsgp_gym/PointMassObstacle-v0", masss=2.0)
