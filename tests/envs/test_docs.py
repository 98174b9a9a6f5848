"""The class docstrings are the spec: every argument and its default appear in ## Arguments."""

import pytest

from afvsgp_gym.envs.franka import FrankaObstacleEnv
from afvsgp_gym.envs.point_mass import PointMassObstacleEnv


def _argument_rows(cls):
    doc = cls.__doc__
    section = doc.split("## Arguments", 1)[1].split("##", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0] not in ("Parameter", "---"):
            names = [n.strip() for n in cells[0].split(",")]
            values = [v.strip() for v in cells[1].split(", ")] if len(names) > 1 else [cells[1]]
            for name, value in zip(names, values, strict=False):
                rows[name] = value
    return rows


def _fmt(value):
    return f'"{value}"' if isinstance(value, str) else str(value)


@pytest.mark.parametrize("cls", [PointMassObstacleEnv, FrankaObstacleEnv])
def test_arguments_table_matches_defaults(cls):
    rows = _argument_rows(cls)
    assert rows.pop("scenario") == '"static"'
    assert set(rows) == set(cls._DEFAULTS)
    for name, default in cls._DEFAULTS.items():
        assert rows[name] == _fmt(default), name
