"""Which code and which machine produced a record: :func:`code_version`, :func:`cpu_model`."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

__all__ = ["code_version", "cpu_model"]


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """``git describe --always --dirty --tags`` of the package's checkout (its commit and
    whether the tree was modified), else the package's version (an installed package). The
    one reading of the code's version: episode records, sweeps and the reproduce protocol."""
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
