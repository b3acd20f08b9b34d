"""The drawing pieces every figure of dmpc shares: a grid of panels, the bounds as dashed red
lines, and when an axis turns logarithmic. Matplotlib is passed in (``plt``), never imported
here, so that the modules that draw decide how it is loaded."""
from __future__ import annotations

import math

import numpy as np

LOG_DECADES = 2.0
"""An axis turns logarithmic when its positive finite values span more than this many decades."""


def panel_grid(plt, panels: int, ncols: int, width: float, height: float, *, title: str = "",
               hidden: frozenset[int] | set[int] = frozenset(), sharex: bool = False, margin: float = 0.0):
    """A figure with ``panels`` axes, ``ncols`` to a row, each about ``width`` x ``height`` inches,
    drawn with ``plt`` (matplotlib.pyplot); ``sharex``: one x axis for all.

    Slots past ``panels`` and those in ``hidden`` are switched off. ``margin`` adds inches to the
    figure's width (room for the row labels); a title adds a line of height.

    Returns
    -------
    (Figure, list of Axes)
        The visible axes, row by row.
    """
    nrows = math.ceil(panels / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(width * ncols + margin, height * nrows + (0.7 if title else 0.6)),
                             squeeze=False, sharex=sharex, layout="constrained")
    if title:
        fig.suptitle(title)
    flat = list(axes.ravel())
    for index, ax in enumerate(flat):
        if index >= panels or index in hidden:
            ax.set_visible(False)
    return fig, [ax for index, ax in enumerate(flat[:panels]) if index not in hidden]


def bound_lines(ax, lower: float, upper: float, label: str | None = None) -> bool:
    """Dashed red lines on ``ax`` at the finite bounds ``lower`` and ``upper``; ``label`` names the
    upper one in a legend. True if a line was drawn."""
    drawn = False
    for value, name in ((upper, "upper"), (lower, "lower")):
        if np.isfinite(value):
            ax.axhline(value, color="red", linewidth=1.0, linestyle="--", label=label if name == "upper" else None)
            drawn = True
    return drawn


def use_log(values: list[np.ndarray]) -> bool:
    """Log scale when the positive finite values span more than ``LOG_DECADES`` decades."""
    data = np.concatenate([np.asarray(v, float).ravel() for v in values]) if values else np.array([])
    pos = data[np.isfinite(data) & (data > 0)]
    return pos.size > 1 and math.log10(pos.max() / pos.min()) > LOG_DECADES


def positive(values: np.ndarray) -> np.ndarray:
    """The values with the non-positive ones masked (NaN), for a log axis."""
    out = np.asarray(values, float).copy()
    out[~(out > 0)] = np.nan
    return out
