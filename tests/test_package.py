"""Package-level checks: import stays light and registers the ids."""

import subprocess
import sys

import gymnasium as gym

import afvsgp_gym


def test_version_is_a_string():
    assert isinstance(afvsgp_gym.__version__, str) and afvsgp_gym.__version__.count(".") == 2


def test_ids_registered():
    assert "afvsgp_gym/PointMassObstacle-v0" in gym.registry


def test_import_does_not_import_mujoco():
    code = "import sys, afvsgp_gym; print('mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_docstring_lists_every_registered_id():
    ids = sorted(i for i in gym.registry if i.startswith("afvsgp_gym/"))
    assert len(ids) == 7
    for env_id in ids:
        assert f"``{env_id}``" in afvsgp_gym.__doc__
