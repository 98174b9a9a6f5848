"""PNG summary of a sweep report: one row per group, three panels.

1. Episodes with cost: the observed rate ``k / n`` (dot; an open dot at the axis' left end when
   ``k = 0``) and the Clopper-Pearson upper bound (bar), on a log axis; ``[k/n]`` in the
   row's label.
2. min h of every episode (dots, jittered) with ``h = 0`` marked.
3. Mean tracking error of every episode over the steps whose reference keeps clear of the
   obstacles (dots).

Uses matplotlib's object API with the Agg canvas (no pyplot state touched).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["plot_report"]


def _label(row: Mapping[str, Any], fields: Sequence[str]) -> str:
    parts = []
    for f in fields:
        v = row.get(f)
        if f == "env" and isinstance(v, str):
            v = v.removeprefix("afvsgp_gym/").removesuffix("-v0")
        v = "-" if v is None else v
        parts.append(f"{v}" if f in ("env", "learner") else f"{f.split('.', 1)[-1]}={v}")
    return " ".join(parts)


def _values(recs: Sequence[Mapping[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in recs])


def plot_report(rep: Mapping[str, Any], groups: Sequence[Sequence[Mapping[str, Any]]],
                path: str | os.PathLike) -> Path:
    """Draw ``rep`` (of :func:`afvsgp_gym.sweep.report.report`) with the per-episode records
    of each of its rows (``groups``, same order) into ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = rep["rows"]
    if len(groups) != len(rows):
        raise ValueError(f"{len(groups)} record groups for {len(rows)} report rows")
    n = len(rows)
    fig = Figure(figsize=(13.0, 1.4 + 0.28 * n), layout="constrained")
    FigureCanvasAgg(fig)
    ax_cost, ax_h, ax_track = fig.subplots(1, 3, sharey=True,
                                           gridspec_kw={"width_ratios": [1.2, 1.0, 1.0]})
    y = np.arange(n)[::-1]
    uppers = np.array([r["cost_rate_upper"] for r in rows], dtype=float)
    left = max(min(uppers.min() / 3.0, 1e-3), 1e-6)
    rng = np.random.default_rng(0)  # jitter only
    for yi, row, recs in zip(y, rows, groups, strict=True):
        k, m = row["episodes_with_cost"], row["episodes"]
        ax_cost.plot([left, row["cost_rate_upper"]], [yi, yi], color="tab:red", lw=4,
                     alpha=0.35, solid_capstyle="butt")
        if k > 0:
            ax_cost.plot(k / m, yi, "o", color="tab:red")
        else:
            ax_cost.plot(left, yi, "o", mfc="white", color="tab:red")
        jitter = rng.uniform(-0.25, 0.25, len(recs))
        ax_h.plot(_values(recs, "min_h"), yi + jitter, ".", ms=3, color="tab:blue", alpha=0.6)
        ax_track.plot(_values(recs, "tracking_error_mean"), yi + jitter, ".", ms=3,
                      color="tab:green", alpha=0.6)
    conf = 100 * rep["confidence"]
    ax_cost.set_xscale("log")
    ax_cost.set_xlim(left / 1.5, 1.0)
    ax_cost.set_xlabel(f"episodes with cost: rate (dot) and {conf:g}% upper bound (bar)")
    ax_h.axvline(0.0, color="k", lw=0.8, ls="--")
    ax_h.set_xlabel("min h per episode (m)")
    ax_track.set_xlabel("mean tracking error per episode (m)")
    ax_cost.set_yticks(y, [f"{_label(r, rep['fields'])}  [{r['episodes_with_cost']}/"
                           f"{r['episodes']}]" for r in rows], fontsize=7)
    ax_cost.set_ylim(-0.7, n - 0.3)
    for ax in (ax_cost, ax_h, ax_track):
        ax.grid(True, axis="x", alpha=0.3)
    fig.suptitle(f"{rep['episodes']} episodes, {n} groups", fontsize=9)
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path
