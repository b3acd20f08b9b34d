"""Figures of a :class:`~dmpc.result.Result`: states, inputs and cost over time.

Axes are in seconds when the scenario has ``dt`` (else steps), labelled with the quantities'
names and units, and the state and input bounds are drawn as dashed lines. The figures are
made with pyplot, so a notebook shows them; a script saves them with ``fig.savefig``.
"""
from __future__ import annotations

import math

import numpy as np

MAX_ROWS = 8
"""Subsystems drawn (the first ones, in scenario order)."""
LOG_DECADES = 2.0


def _grid(plt, rows: int, cols: int, title: str):
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols + 0.6, 2.2 * rows + 0.7), squeeze=False,
                             sharex=True, layout="constrained")
    fig.suptitle(title)
    return fig, axes


def _bound_lines(ax, q) -> bool:
    drawn = False
    for value in (q.lower, q.upper):
        if np.isfinite(value):
            ax.axhline(value, color="red", linestyle="--", linewidth=1.0)
            drawn = True
    return drawn


def _signals(plt, result, kind: str, bounds: bool):
    """One row per subsystem, one column per component (states: kind 'x'; inputs: 'u')."""
    names = result.names[:MAX_ROWS]
    values = result.x if kind == "x" else result.u
    quantities = result.states if kind == "x" else result.inputs
    cols = max(len(quantities[name]) for name in names)
    what = "states" if kind == "x" else "inputs"
    note = f" (first {MAX_ROWS} of {len(result.names)} subsystems)" if len(result.names) > MAX_ROWS else ""
    fig, axes = _grid(plt, len(names), cols, f"{what} of '{result.summary.get('scenario', '')}'{note}")
    t = result.t
    for r, name in enumerate(names):
        for c in range(cols):
            ax = axes[r, c]
            if c >= len(quantities[name]):
                ax.set_visible(False)
                continue
            q = quantities[name][c]
            style = dict(drawstyle="steps-post") if kind == "u" else dict(marker=".", markersize=3)
            series = values[name][:, c]
            if kind == "u":  # u(k) holds over [t_k, t_k+1): repeat the last one to show its period
                series = np.append(series, series[-1:]) if series.size else np.full(t.shape, np.nan)
            ax.plot(t, series, color=f"C{c}", **style)
            if bounds and _bound_lines(ax, q) and r == 0 and c == 0:
                ax.plot([], [], color="red", linestyle="--", linewidth=1.0, label="bounds")
                ax.legend(loc="best", fontsize=7)
            ax.axhline(0.0, color="grey", linewidth=0.5)
            ax.set_ylabel(q.label)
            ax.set_title(f"subsystem {name}", fontsize=9)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel(result.time_label)
    for c in range(cols):
        axes[-1, c].set_xlabel(result.time_label)
    return fig


def _cost(plt, result):
    fig, ax = plt.subplots(figsize=(6.0, 3.4), layout="constrained")
    J = np.asarray(result.J, float)
    pos = J[np.isfinite(J) & (J > 0)]
    log = pos.size > 1 and math.log10(pos.max() / pos.min()) > LOG_DECADES
    ax.plot(result.t[:-1], np.where(J > 0, J, np.nan) if log else J, marker=".", label="J(k)")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(result.time_label)
    ax.set_ylabel("J" + (" (log scale)" if log else ""))
    ax.set_title(f"cost, closed loop {result.cost:.4g} (verdict {result.verdict})")
    ax.grid(alpha=0.3)
    return fig


def plot_result(result, bounds: bool = True) -> dict:
    """``{"states": Figure, "inputs": Figure, "cost": Figure}`` for a Result."""
    import matplotlib.pyplot as plt

    return {"states": _signals(plt, result, "x", bounds), "inputs": _signals(plt, result, "u", bounds),
            "cost": _cost(plt, result)}
