"""PNG figures in the style of the paper's Figs. 2 and 4, from plain arrays.

Uses matplotlib's object API with the Agg canvas (no pyplot, no global backend switch), so it
runs headless and never touches the caller's matplotlib state.

- :func:`plot_uncertainty` (Fig. 2): per method, the true uncertainty ``delta_b_true`` (blue)
  against the one-step-ahead prediction (red) with its 95% band (mean +- 1.96 std), the motion
  switch marked by a dashed vertical line.
- :func:`plot_barrier` (Fig. 4): per method, ``h`` over time with ``h = 0`` marked.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["plot_barrier", "plot_uncertainty"]

Z95 = 1.959963984540054


def _figure(n: int, width: float = 7.0, height: float = 2.2):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height * max(n, 1)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(max(n, 1), 1, sharex=True, squeeze=False)[:, 0]
    return fig, axes


def plot_uncertainty(
    series: Mapping[str, Mapping[str, np.ndarray]],
    path: str | os.PathLike,
    *,
    switch_time: float | None = None,
    title: str | None = None,
    ylabel: str = r"$\Delta B^{(2)}$ [m/s$^2$]",
) -> Path:
    """Fig. 2-like panels, one per method.

    ``series[name]`` has arrays ``t``, ``truth``, ``mean``, ``std`` of equal length (NaN entries,
    e.g. steps without a prediction, are left blank).
    """
    fig, axes = _figure(len(series))
    for ax, (name, s) in zip(axes, series.items(), strict=False):
        t = np.asarray(s["t"], dtype=float)
        mean = np.asarray(s["mean"], dtype=float)
        std = np.asarray(s["std"], dtype=float)
        ax.plot(t, np.asarray(s["truth"], dtype=float), color="tab:blue", lw=1.0,
                label=r"true $\Delta B$")
        ax.plot(t, mean, color="tab:red", lw=1.0, label="prediction")
        ax.fill_between(t, mean - Z95 * std, mean + Z95 * std, color="tab:red", alpha=0.2,
                        lw=0, label="95% band")
        if switch_time is not None:
            ax.axvline(switch_time, color="tab:green", ls="--", lw=1.0, label="switch y -> z")
        ax.set_title(name, loc="left", fontsize=9)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right", ncol=4)
    axes[-1].set_xlabel("time [s]")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_barrier(
    series: Mapping[str, Mapping[str, np.ndarray]],
    path: str | os.PathLike,
    *,
    title: str | None = None,
    margin: float | None = None,
) -> Path:
    """Fig. 4-like panels: ``h`` over time per method (``series[name]`` has ``t``, ``h``).

    ``h = 0`` is a red dashed line; violations (h < 0) are shaded. ``margin`` draws an extra
    dotted line (e.g. the paper's 0.07 m real-robot margin).
    """
    fig, axes = _figure(len(series), height=1.9)
    for ax, (name, s) in zip(axes, series.items(), strict=False):
        t = np.asarray(s["t"], dtype=float)
        h = np.asarray(s["h"], dtype=float)
        ax.plot(t, h, color="tab:blue", lw=1.0, label="h(x)")
        ax.axhline(0.0, color="tab:red", ls="--", lw=1.0, label="h = 0")
        if margin is not None:
            ax.axhline(margin, color="gray", ls=":", lw=1.0, label=f"h = {margin:g}")
        neg = h < 0
        if neg.any():
            ax.fill_between(t, h, 0.0, where=neg, color="tab:red", alpha=0.3, lw=0,
                            label="violation")
        finite = h[np.isfinite(h)]
        min_h = float(finite.min()) if finite.size else float("nan")
        ax.set_title(f"{name}   (min h = {min_h:.4f} m, {int(neg.sum())} steps with h < 0)",
                     loc="left", fontsize=9)
        ax.set_ylabel("h [m]", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right", ncol=4)
    axes[-1].set_xlabel("time [s]")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _save(fig, path: str | os.PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path
