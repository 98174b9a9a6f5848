"""PNG summary of a sweep report: one row per group, three panels, and a reliability
diagram of the learned band when the records carry its calibration counts.

1. Episodes with cost: the observed rate ``k / n`` (dot; an open dot at the axis' left end when
   ``k = 0``) and the Clopper-Pearson upper bound (bar), on a log axis; ``[k/n]`` in the
   row's label.
2. min h of every episode (dots, jittered) with ``h = 0`` marked.
3. Mean tracking error of every episode over the steps whose reference keeps clear of the
   obstacles (dots).
4. Reliability of the learned band (:func:`reliability_points`), one line per group: the share
   of (barrier, step) pairs outside the band as promised (x) against as observed (y), on log
   axes, for the two-sided 1, 2 and 3 std bands and the one-sided band of the chance
   constraint. A calibrated band lies on the diagonal; above it the band is too narrow.

Uses matplotlib's object API with the Agg canvas (no pyplot state touched).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["plot_report", "reliability_points"]

#: the promised share outside the two-sided 1, 2 and 3 std bands of a Gaussian
_TWO_SIDED = (0.31731050786291404, 0.04550026389635842, 0.0026997960632601866)


def _label(row: Mapping[str, Any], fields: Sequence[str]) -> str:
    parts = []
    for f in fields:
        v = row.get(f)
        if f == "env" and isinstance(v, str):
            v = v.removeprefix("afvsgp_gym/").removesuffix("-v0")
        v = "-" if v is None else v
        parts.append(f"{v}" if f in ("env", "learner") else f"{f.split('.', 1)[-1]}={v}")
    return " ".join(parts)


def _miss_promised(rec: Mapping[str, Any]) -> float:
    """``Phi(-beta)`` of the record's filter (its ``beta`` or ``miss_probability`` option, else
    the default ``beta``)."""
    from afvsgp_gym.cbf.calibration import beta_for_miss_probability, miss_target
    from afvsgp_gym.cbf.config import DEFAULT_BETA

    kwargs = (rec.get("config") or {}).get("filter_kwargs") or {}
    if kwargs.get("miss_probability") is not None:
        return miss_target(beta_for_miss_probability(kwargs["miss_probability"]))
    return miss_target(kwargs.get("beta", DEFAULT_BETA))


def reliability_points(recs: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray] | None:
    """The band's reliability over the episodes ``recs``, pooled over their (barrier, step)
    pairs: ``(promised, observed)`` shares outside the band, each of shape (4,): the
    two-sided 1, 2, 3 std bands (31.7, 4.55, 0.27 %) and the one-sided band of the chance
    constraint (``Phi(-beta)``, its misses). None when no pair was scored. The records' betas
    must agree (``ValueError`` otherwise)."""
    scored = [r for r in recs if (r.get("calibration_samples") or 0) > 0]
    if not scored:
        return None
    promised = {_miss_promised(r) for r in scored}
    if len(promised) > 1:
        raise ValueError(f"the records promise different miss probabilities: {sorted(promised)}")
    n = sum(int(r["calibration_samples"]) for r in scored)
    inside = [sum(int(r[f"calibration_within_{k}std"] or 0) for r in scored) for k in (1, 2, 3)]
    misses = sum(int(r.get("calibration_misses") or 0) for r in scored)
    observed = np.array([1.0 - i / n for i in inside] + [misses / n])
    return np.array([*_TWO_SIDED, promised.pop()]), observed


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
    points = [_reliability_or_none(recs) for recs in groups]
    calibrated = any(p is not None for p in points)
    fig = Figure(figsize=(13.0 + 4.5 * calibrated, max(1.4 + 0.28 * n, 4.0 * calibrated)),
                 layout="constrained")
    FigureCanvasAgg(fig)
    if calibrated:
        ax_cost, ax_h, ax_track, ax_rel = fig.subplots(
            1, 4, gridspec_kw={"width_ratios": [1.2, 1.0, 1.0, 1.5]})
        for ax in (ax_h, ax_track):
            ax.sharey(ax_cost)
            ax.tick_params(labelleft=False)
        _plot_reliability(ax_rel, rows, points, rep["fields"])
    else:
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


def _reliability_or_none(recs):
    """:func:`reliability_points`, None for a group whose records promise different miss
    probabilities (no one diagonal to compare them with)."""
    try:
        return reliability_points(recs)
    except ValueError:
        return None


def _plot_reliability(ax, rows, points, fields) -> None:
    """Panel 4: promised against observed shares outside the band, one line per group."""
    lo = 1e-4
    for row, pts in zip(rows, points, strict=True):
        if pts is None:
            continue
        promised, observed = pts
        shown = np.maximum(observed, lo)  # a share of 0 drawn at the axis' bottom
        line, = ax.plot(promised[:3], shown[:3], "o-", ms=4, lw=1,
                        label=_label(row, fields))
        ax.plot(promised[3], shown[3], "s", ms=6, color=line.get_color())
    ax.plot([lo, 1.0], [lo, 1.0], color="k", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, 1.0)
    ax.set_ylim(lo, 1.0)
    ax.set_xlabel("promised share outside the band")
    ax.set_ylabel("observed share outside the band")
    ax.set_title("the band's reliability (dots: 1, 2, 3 std; square: one-sided)", fontsize=8)
    ax.set_aspect("equal")
    ax.grid(True, which="major", alpha=0.3)
    if len(rows) <= 12:
        ax.legend(fontsize=6, loc="lower right")
