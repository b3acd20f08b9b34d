"""Figures of a :class:`~dmpc.api.result.Result`: states, inputs and cost over time.

Drawn by the same code as ``dmpc report`` (:mod:`dmpc.plots.report`): axes in seconds when the
scenario has ``dt`` (else steps), labelled with the quantities' names and units, the bounds
dashed; with setpoints, the targets applied dashed, the setpoints dotted and the steps where they
changed marked on the cost; with estimation, the state estimates dashed beside the states and a
figure of the outputs measured, the disturbance estimates and the innovation. The figures are made
with pyplot, so a notebook shows them; a script saves them with ``fig.savefig``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np

from dmpc.plots.estimates import estimates_figure
from dmpc.plots.report import (
    STYLE,
    RunData,
    _panel_note,
    _series_figure,
    _shown,
    _signal_figure,
    _style,
    setpoint_changes,
)
from dmpc.plots.targets import Tracked
from dmpc.records.reader import Estimates

TRACKING = ("setpoint", "setpoint_u", "reference", "reference_u", "target", "target_u")


def run_data(result) -> RunData:
    """The figures' view of the Result ``result`` (the arrays of its run folder, as ``dmpc report``
    reads them)."""
    names = list(result.names)
    states = [result.states[name] for name in names]
    inputs = [result.inputs[name] for name in names]
    x = np.hstack([result.x[name] for name in names])
    S = np.asarray(result.summary.get("S", []), float)
    P = [result.design.P[name] for name in names] if result.design is not None else None
    return RunData(path=Path(result.folder) if result.folder is not None else Path("."), method=result.method,
                   scenario=str(result.summary.get("scenario", "")), names=names, n=[len(q) for q in states],
                   m=[len(q) for q in inputs], lower=[np.array([q.lower for q in qs]) for qs in inputs],
                   upper=[np.array([q.upper for q in qs]) for qs in inputs], P=P, x=x,
                   u=np.hstack([result.u[name] for name in names]),
                   alpha=np.hstack([result.alpha[name] for name in names]), beta=np.asarray(result.beta, float),
                   r=None, J=np.asarray(result.J, float), S=S if S.shape == (x.shape[0],) else np.full(x.shape[0], np.nan),
                   states=states, inputs=inputs, dt=result.dt, tracked=tracked_of(result),
                   estimates=estimates_of(result))


def tracked_of(result) -> Tracked | None:
    """The setpoints and targets of the Result ``result`` stacked over its subsystems (as trajectory.npz
    holds them), or None when the run requested nothing."""
    names = list(result.names)
    mappings = {key: getattr(result, key) for key in TRACKING}
    if not all(all(name in mapping for name in names) for mapping in mappings.values()):
        return None
    return Tracked.of({key: np.hstack([mapping[name] for name in names]) for key, mapping in mappings.items()})


def estimates_of(result) -> Estimates | None:
    """What the controllers of a run saw, stacked over its subsystems (as trajectory.npz holds it).

    Parameters
    ----------
    result : dmpc.Result

    Returns
    -------
    Estimates or None
        None for a run without estimation.
    """
    names = list(result.names)
    if not all(name in result.x_hat for name in names):
        return None
    steps = result.innovation.shape[0]
    p = [result.y[name].shape[1] for name in names]
    asked = result.setpoint_y if all(name in result.setpoint_y for name in names) else {
        name: np.full((steps, size), np.nan) for name, size in zip(names, p)}
    return Estimates(y=np.hstack([result.y[name] for name in names]),
                     x_hat=np.hstack([result.x_hat[name] for name in names]),
                     d_hat=np.hstack([result.d_hat[name] for name in names]),
                     innovation=np.asarray(result.innovation, float),
                     setpoint_y=np.hstack([asked[name] for name in names]), p=p,
                     nd=[result.d_hat[name].shape[1] for name in names],
                     outputs=[result.outputs[name] for name in names],
                     disturbances=[result.disturbances[name] for name in names],
                     C=[result.C[name] for name in names] if all(name in result.C for name in names) else None)


def plot_result(result, bounds: bool = True) -> dict:
    """``{"states": Figure, "inputs": Figure, "cost": Figure}`` for the Result ``result``, and with
    estimation ``"estimates"``; ``bounds``: the constraint bounds drawn as dashed lines."""
    import matplotlib
    import matplotlib.pyplot as plt

    run = run_data(result)
    head = f"{run.scenario}, {run.method}"
    with plt.rc_context(cast(Any, STYLE)):  # matplotlib types its keys as a Literal of every rc name
        figures = {"states": _signal_figure(plt, [(run, run.method)], "x", f"{head}: states", bounds),
                   "inputs": _signal_figure(plt, [(run, run.method)], "u", f"{head}: inputs", bounds),
                   "cost": _series_figure(plt, [("J(k)", run.J, dict(_style(run.method), color="C0"), run.method)],
                                          "$J(k) = \\sum_i J_i^*(k)$",
                                          f"cost, closed loop {result.cost:.4g} (verdict {result.verdict})", run,
                                          setpoint_changes(run))}
        if run.estimates is not None:
            figures["estimates"] = estimates_figure(plt, run, f"{head}: outputs measured and disturbance estimates"
                                                    + _panel_note(run.M), _shown(run.M))
        interactive = matplotlib.is_interactive()
    # a backend loaded by the first figure (a notebook's) may have turned interactive mode on, which
    # the context would undo on leaving: a notebook would then show no later call's figures
    matplotlib.interactive(interactive)
    return figures
