"""Test-wide settings: headless MuJoCo rendering."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
