"""Argument checks shared by the package: each raises ``ValueError`` naming the argument."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

__all__ = ["check_choice", "check_int", "check_number"]


def check_number(
    name: str,
    value: Any,
    strictly_positive: bool = False,
    *,
    low: float | None = 0.0,
    high: float | None = None,
    high_open: bool = False,
) -> float:
    """``float(value)`` if finite and in range, else ``ValueError`` naming ``name``.

    The default range is ``value >= 0`` (``> 0`` with ``strictly_positive``); ``low=None``
    drops the lower bound; ``high`` adds ``value <= high`` (``< high`` with ``high_open``).
    """
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    ok = math.isfinite(x)
    if ok and low is not None:
        ok = x > low if strictly_positive else x >= low
    if ok and high is not None:
        ok = x < high if high_open else x <= high
    if not ok:
        parts = []
        if low is not None:
            parts.append(f"{'>' if strictly_positive else '>='} {low:g}")
        if high is not None:
            parts.append(f"{'<' if high_open else '<='} {high:g}")
        rng = " and ".join(parts)
        raise ValueError(f"{name} must be a finite number{' ' + rng if rng else ''}, got {value!r}")
    return x


def check_int(name: str, value: Any, minimum: int = 0) -> int:
    """``int(value)`` for an integer ``>= minimum`` (bools refused), else ``ValueError``."""
    if isinstance(value, bool) or not isinstance(value, (int,)) and not (
        hasattr(value, "__index__")
    ):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    v = int(value)
    if v < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return v


def check_choice(name: str, value: Any, valid: Sequence[str]) -> str:
    """``value`` if it is one of ``valid``, else ``ValueError`` listing the choices."""
    if not isinstance(value, str) or value not in valid:
        raise ValueError(f"{name}={value!r} is not valid; choose one of {list(valid)}")
    return value
