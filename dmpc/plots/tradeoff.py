"""The event trigger's trade-off: QP solves (each one a plan message) and bytes sent against the
closed-loop cost, over the trigger's cost threshold (``options.trigger_cost``), with solving at
every step (``always``) as the reference.

A sweep is a dict as :func:`dmpc.bench.trigger.sweep` returns it: ``case``, ``M``, ``always`` (a
row) and ``event`` (a row per threshold), each row with ``trigger_cost``, ``solves``, ``bytes`` and
``closed_loop_cost``. Three panels: what is sent against the threshold, the cost against the
threshold, and the two against each other. Counts are in % of the ``always`` run's, costs in
parts per million (ppm) of its cost; a threshold of 0 sits one decade left of the smallest other.
Matplotlib is passed in (``plt``), as in :mod:`dmpc.plots.style`.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dmpc.plots.report import DPI, STYLE
from dmpc.plots.style import panel_grid

TRADEOFF_FIGURE = "trigger_tradeoff"
ROUNDING_PPM = 1e-6
"""Cost changes smaller than this (1e-12 of the cost: rounding) are drawn as 0."""
SENT = (("solves", "QP solves = plan messages", "-", "o"), ("bytes", "bytes sent", "--", "s"))
"""The counts drawn: key, label, line style, marker."""


def share(sweep: dict, key: str) -> np.ndarray:
    """``key`` of each event row of ``sweep`` in % of the ``always`` row's, shape (thresholds,)."""
    ref = sweep["always"].get(key) or np.nan
    return np.array([100.0 * (row.get(key) or np.nan) / ref for row in sweep["event"]], float)


def cost_ppm(sweep: dict) -> np.ndarray:
    """Each event row's closed-loop cost over the ``always`` row's in ``sweep``, minus 1, in ppm."""
    ref = sweep["always"]["closed_loop_cost"]
    ppm = np.array([1e6 * (row["closed_loop_cost"] / ref - 1.0) for row in sweep["event"]], float)
    ppm[np.abs(ppm) < ROUNDING_PPM] = 0.0
    return ppm


def threshold_axis(sweeps: list[dict]) -> tuple[float, float]:
    """(where a threshold of 0 is drawn on the log axis, the smallest positive threshold) over ``sweeps``."""
    positive = [row["trigger_cost"] for s in sweeps for row in s["event"] if row["trigger_cost"] > 0]
    smallest = min(positive, default=1.0)
    return smallest / 10.0, smallest


def positions(sweep: dict, zero_at: float) -> np.ndarray:
    """The thresholds of ``sweep`` on the log axis (0 at ``zero_at``)."""
    return np.array([row["trigger_cost"] or zero_at for row in sweep["event"]], float)


def threshold_text(cost: float) -> str:
    """The threshold ``cost`` as the legend and the labels give it: ``0``, ``1e-04``, ``0.1``, ``10``."""
    return "0" if cost == 0 else f"{cost:g}"


def sweep_label(sweep: dict) -> str:
    """The case of ``sweep``: ``paper (M = 4)``, ``chain (M = 64)``."""
    return f"{sweep['case']} (M = {sweep['M']})"


def _log_thresholds(ax, sweeps: list[dict]) -> None:
    """A log x axis of the thresholds, with 0 named where it is drawn."""
    zero_at, _ = threshold_axis(sweeps)
    ax.set_xscale("log")
    ticks = sorted({p for s in sweeps for p in positions(s, zero_at)})
    ax.set_xticks(ticks, [threshold_text(0.0 if t == zero_at else t) for t in ticks], rotation=45)
    ax.minorticks_off()
    ax.set_xlabel("cost threshold trigger_cost")


def sent_panel(ax, sweeps: list[dict]) -> None:
    """What is sent against the threshold, in % of ``always``, one line per sweep of ``sweeps``, on ``ax``."""
    zero_at, _ = threshold_axis(sweeps)
    for index, s in enumerate(sweeps):
        for key, label, style, marker in SENT:
            ax.plot(positions(s, zero_at), share(s, key), linestyle=style, marker=marker, color=f"C{index}",
                    markerfacecolor="none" if style != "-" else None, label=f"{sweep_label(s)}: {label}")
    ax.axhline(100.0, color="black", linewidth=1.0, linestyle=":", label="always (every agent, every step)")
    _log_thresholds(ax, sweeps)
    ax.set_ylabel("% of always's")
    ax.set_ylim(0, 110)
    ax.set_title("sent, against the threshold")
    ax.legend(loc="lower left", framealpha=0.85)


def cost_panel(ax, sweeps: list[dict]) -> None:
    """The closed-loop cost against the threshold, in ppm over ``always``'s, one line per sweep of
    ``sweeps``, on ``ax``."""
    zero_at, _ = threshold_axis(sweeps)
    for index, s in enumerate(sweeps):
        ax.plot(positions(s, zero_at), cost_ppm(s), marker="o", color=f"C{index}", label=sweep_label(s))
    ax.axhline(0.0, color="black", linewidth=1.0, linestyle=":", label="always")
    _log_thresholds(ax, sweeps)
    _cost_scale(ax, sweeps, "y")
    ax.set_ylabel("closed-loop cost over always's - 1 (ppm)")
    ax.set_title("closed-loop cost, against the threshold")
    ax.legend(loc="upper left", framealpha=0.85)


def tradeoff_panel(ax, sweeps: list[dict]) -> None:
    """QP solves (each a plan message) against the closed-loop cost, each point a threshold (named), one
    line per sweep of ``sweeps``, on ``ax``."""
    for index, s in enumerate(sweeps):
        ppm, solves = cost_ppm(s), share(s, "solves")
        ax.plot(ppm, solves, linestyle="none", marker="o", color=f"C{index}", label=sweep_label(s))
        _name_points(ax, ppm, solves, [row["trigger_cost"] for row in s["event"]], f"C{index}")
    ax.plot([0.0], [100.0], marker="*", markersize=11, color="black", linestyle="none", label="always")
    _cost_scale(ax, sweeps, "x")
    ax.set_xlabel("closed-loop cost over always's - 1 (ppm)")
    ax.set_ylabel("QP solves = plan messages (% of always's)")
    ax.set_ylim(0, 110)
    ax.set_title("solves against cost, by threshold")
    ax.legend(loc="lower left", framealpha=0.85)


def _name_points(ax, x: np.ndarray, y: np.ndarray, costs: list[float], color: str) -> None:
    """Write the threshold beside each point, above and below in turn; thresholds that gave the same
    point share one label."""
    groups: dict[tuple[float, float], list[float]] = {}
    for xi, yi, cost in zip(x, y, costs):
        groups.setdefault((round(float(xi), 9), round(float(yi), 6)), []).append(cost)
    for index, ((xi, yi), same) in enumerate(groups.items()):
        text = threshold_text(same[0]) if len(same) == 1 else f"{threshold_text(same[0])}..{threshold_text(same[-1])}"
        ax.annotate(text, (xi, yi), textcoords="offset points", xytext=(5, 4 if index % 2 == 0 else -10), fontsize=7,
                    color=color)


def _cost_scale(ax, sweeps: list[dict], axis: str) -> None:
    """A symmetric log scale on ``axis`` when the cost changes span more than a decade around 0."""
    values = np.concatenate([cost_ppm(s) for s in sweeps]) if sweeps else np.zeros(0)
    nonzero = np.abs(values[np.isfinite(values) & (values != 0)])
    if nonzero.size and nonzero.max() / nonzero.min() > 10:
        linthresh = 10.0 ** math.floor(math.log10(nonzero.min()))
        (ax.set_xscale if axis == "x" else ax.set_yscale)("symlog", linthresh=linthresh)


def tradeoff_figure(plt, sweeps: list[dict], title: str):
    """The three panels of the trade-off (:func:`sent_panel`, :func:`cost_panel`, :func:`tradeoff_panel`)
    of ``sweeps``, titled ``title``, drawn with ``plt`` (matplotlib.pyplot)."""
    fig, axes = panel_grid(plt, 3, 3, 4.4, 3.8, title=title)
    sent_panel(axes[0], sweeps)
    cost_panel(axes[1], sweeps)
    tradeoff_panel(axes[2], sweeps)
    return fig


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_tradeoff(sweeps: list[dict], folder: Path, title: str | None = None) -> Path | None:
    """Write ``folder/trigger_tradeoff.png`` (None when no sweep has an event row).

    Parameters
    ----------
    sweeps : list of dict
        As :func:`dmpc.bench.trigger.sweep` returns them.
    folder : Path
        Created if needed.
    title : str, optional
        Default: says what is compared.
    """
    sweeps = [s for s in sweeps if s.get("event") and s.get("always", {}).get("closed_loop_cost")]
    if not sweeps:
        return None
    plt = _pyplot()
    steps = ", ".join(f"{sweep_label(s)} {s['steps']} steps" for s in sweeps)
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / f"{TRADEOFF_FIGURE}.png"
    with plt.rc_context(STYLE):
        fig = tradeoff_figure(plt, sweeps, title or f"Event trigger against solving at every step ({steps})")
        try:
            fig.savefig(target, dpi=DPI)
        finally:
            plt.close(fig)
    return target
