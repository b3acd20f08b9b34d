"""What the controllers of a run with ``estimation`` saw, as the figures draw it (docs/algorithm.md,
"Offset-free tracking"): the state estimates x^ (dashed, beside the plant's states), the outputs
the plant measured (crosses; on a state's panel where the output is that state alone), the
disturbance estimates d^ and the innovation per step.

Drawn only for a run with estimation; a run without it draws as it did before. Matplotlib is passed
in (``plt``, an ``Axes``), never imported here.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from dmpc.plots.style import panel_grid, positive, use_log
from dmpc.plots.targets import SETPOINT_LABEL, SETPOINT_STYLE, held, unique_legend

if TYPE_CHECKING:
    from dmpc.plots.report import RunData

ESTIMATE_LABEL = "estimate $\\hat{x}$"
MEASURED_LABEL = "measured $y$"
ESTIMATE_STYLE = dict(linestyle="--", linewidth=1.3, alpha=0.9, zorder=2.2)
"""x^ in its state's colour, dashed (the target applied is black and dashed, held over each step)."""
MEASURED_STYLE = dict(linestyle="none", marker="x", markersize=4, markeredgewidth=1.0, alpha=0.8, zorder=2.3)
MAX_OUTPUTS = 4
"""Outputs drawn per subsystem in the estimates figure (the first ones)."""


def draw_state_estimates(ax, run: RunData, i: int, j: int) -> None:
    """Draw a state's estimate x^ (dashed, in the state's colour) and the outputs measured that are
    this state alone (crosses), at steps 0 .. K-1; nothing for a run without estimation.

    Parameters
    ----------
    ax : matplotlib Axes
        The panel of the state.
    run : RunData
        The run (:class:`dmpc.plots.report.RunData`), its ``estimates`` None without estimation.
    i, j : int
        The subsystem, and the state's index in it.
    """
    e = run.estimates
    if e is None:
        return
    import matplotlib.patheffects as effects  # matplotlib only where a figure is drawn

    column = run.state_slice(i).start + j
    times = run.times(e.x_hat.shape[0])
    # a white edge: the dashes stay visible on the state's own line and markers, of the same colour
    ax.plot(times, e.x_hat[:, column], color=f"C{j}", label=ESTIMATE_LABEL,
            path_effects=[effects.withStroke(linewidth=3.2, foreground="white")], **ESTIMATE_STYLE)
    start = e.output_slice(i).start
    for r, state in e.measured(i).items():
        if state == j:
            ax.plot(times, e.y[:, start + r], color=f"C{j}", label=MEASURED_LABEL, **MEASURED_STYLE)


def estimates_figure(plt, run: RunData, title: str, shown: int):
    """The outputs measured, the disturbance estimates and the innovation of a run with estimation.

    A row per subsystem: a panel per output (the first ``MAX_OUTPUTS``) with the values measured
    (crosses) and, where an output was requested, its setpoint (dotted, held over each step), and
    in the last column its disturbance estimates d^, one line each. Below, the innovation
    ||y(k) - C x^(k|k-1) - C_d d^(k|k-1)||_inf, on a log scale when it spans more than two decades.

    Parameters
    ----------
    plt : module
        matplotlib.pyplot.
    run : RunData
        The run (:class:`dmpc.plots.report.RunData`), with ``estimates``.
    title : str
        The figure's title.
    shown : int
        The subsystems drawn: the first ``shown``.

    Returns
    -------
    Figure
    """
    e = run.estimates
    assert e is not None  # drawn for runs with estimation only
    outputs = [min(p, MAX_OUTPUTS) for p in e.p[:shown]]
    cols = max(outputs, default=0) + 1
    panels = (shown + 1) * cols
    hidden = {i * cols + r for i in range(shown) for r in range(outputs[i], cols - 1)}
    hidden |= set(range(shown * cols + 1, panels))
    fig, axes = panel_grid(plt, panels, cols, 3.4, 2.3, hidden=hidden, sharex=True)
    steps = e.y.shape[0]
    times, held_times = run.times(steps), run.times(steps + 1)
    slots = iter(axes)
    signals = []
    for i in range(shown):
        start = e.output_slice(i).start
        for r in range(outputs[i]):
            ax = next(slots)
            signals.append(ax)
            ax.plot(times, e.y[:, start + r], color=f"C{r}", label=MEASURED_LABEL,
                    **dict(MEASURED_STYLE, linestyle="-", linewidth=0.6))
            asked = e.setpoint_y[:, start + r]
            if np.isfinite(asked).any():
                ax.plot(held_times, held(asked), drawstyle="steps-post", label=SETPOINT_LABEL, **SETPOINT_STYLE)
            more = f" (first {MAX_OUTPUTS} of {e.p[i]} outputs)" if r == 0 and e.p[i] > MAX_OUTPUTS else ""
            ax.set_title(f"subsystem {run.names[i]}: output{more}")
            ax.set_ylabel(e.outputs[i][r].label)
            ax.set_xlabel(run.time_label)
        ax = next(slots)
        d = e.d_hat[:, e.disturbance_slice(i)]
        for r in range(d.shape[1]):
            ax.plot(times, d[:, r], color=f"C{r}", label=e.disturbances[i][r].label)
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_title(f"subsystem {run.names[i]}: disturbance estimates")
        ax.set_ylabel("$\\hat{d}$")
        ax.set_xlabel(run.time_label)
        if d.shape[1]:
            ax.legend(loc="best", framealpha=0.85)
    ax = next(slots)
    log = use_log([e.innovation])
    ax.plot(times, positive(e.innovation) if log else e.innovation, color="black", marker="o", markersize=2.5)
    if log:
        ax.set_yscale("log")
    ax.set_title("innovation")
    ax.set_ylabel("$\\|y - C\\hat{x}^- - C_d\\hat{d}^-\\|_\\infty$" + (" (log)" if log else ""))
    ax.set_xlabel(run.time_label)
    handles, labels = unique_legend(signals)
    if labels:
        fig.legend(handles, labels, loc="outside lower center", ncols=len(labels), framealpha=0.9)
    fig.suptitle(title)
    return fig
