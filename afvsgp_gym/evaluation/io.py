"""Plain JSON data and writable output paths (checked before a long run starts)."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["check_writable", "jsonable"]


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
