"""The result of a run, read from its run folder and indexed by subsystem name (``dmpc.Result``).

``dmpc.simulate`` and ``dmpc.run`` write a run folder and return :func:`load_run` of it, so a
result read back later is the same. The folder is read by :func:`dmpc.records.reader.read_run`,
which also splits older run folders (whose ``trajectory.npz`` has no names and sizes) with the
sizes of their ``scenario.yaml`` or ``design.json``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from dmpc.core.quantities import Quantity, time_axis, time_label
from dmpc.methods import DEFAULT_METHOD
from dmpc.offline.record import Design
from dmpc.plots.result import plot_result
from dmpc.records.files import SUMMARY, TRAJECTORY
from dmpc.records.reader import (
    STATE_KEYS,
    TRACKING_KEYS,
    Estimates,
    RunFolderNotReadable,
    is_finished_run_folder,
    read_run,
    tracking_arrays,
)


@dataclass(frozen=True, eq=False, repr=False)
class Result:
    """A run's trajectories and verdict.

    Attributes
    ----------
    names : tuple of str
        Subsystem names, in scenario order.
    t : ndarray, shape (K+1,)
        Time of x(0) .. x(K): seconds when the scenario has ``dt``, else the step index k.
    dt : float or None
        The scenario's sampling period in seconds.
    x : mapping name -> ndarray, shape (K+1, n_i)
        States x_i(0) .. x_i(K).
    u : mapping name -> ndarray, shape (K, m_i)
        Inputs applied u_i(0) .. u_i(K-1).
    w : mapping name -> ndarray, shape (K, n_i)
        The plant disturbance w_i(k) added to x_i(k+1) (zeros without one).
    alpha : mapping name -> ndarray, shape (K+1, n_i)
        Terminal box centres alpha_i(k) (zeros for the methods without a box).
    beta : ndarray, shape (K+1,)
        Terminal box radius beta(k) (NaN for the methods without a box).
    J : ndarray, shape (K,)
        The sum of the agents' optimal costs at each step.
    cost : float
        Closed-loop cost sum_k x(k)'Q x(k) + u(k)'R u(k).
    verdict : str
        ``ok`` or ``failed`` (the reasons are in ``summary['failures']``).
    summary : dict
        ``summary.json``.
    design : Design
    states, inputs : mapping name -> tuple of Quantity
        Names, units and bounds of each subsystem's states and inputs.
    method : str
    folder : Path or None
        The run folder (None when the run was written to a temporary folder).
    setpoint, setpoint_u : mapping name -> ndarray, shape (K, n_i) and (K, m_i)
        The components requested at each step (NaN where free; all NaN without setpoints).
    reference, reference_u : mapping name -> ndarray, shape (K, n_i) and (K, m_i)
        The target of each step's request: a steady state of the coupled system (the nearest
        admissible one when the request is unreachable; zeros without setpoints).
    target, target_u : mapping name -> ndarray, shape (K, n_i) and (K, m_i)
        The target each step applied, moved toward the reference by the reference governor.
    governor : ndarray, shape (K,)
        The fraction of the way to the reference the applied target moved at each step (1: there).
    y : mapping name -> ndarray, shape (K, p_i)
        With ``estimation``: the outputs y_i(k) = C_i x_i(k) the plant measured at steps 0 .. K-1
        (with its measurement noise). An empty mapping for a run without estimation, as are the
        other fields of estimation below.
    x_hat : mapping name -> ndarray, shape (K, n_i)
        With ``estimation``: the state estimates x^_i(k|k) the controllers worked from at steps
        0 .. K-1 (row k beside ``x[name][k]``, the plant's own state).
    d_hat : mapping name -> ndarray, shape (K, n_d,i)
        With ``estimation``: the disturbance estimates d^_i(k|k); n_d,i = p_i for the ``output``
        disturbance model, m_i for ``input``.
    innovation : ndarray, shape (K,)
        With ``estimation``: ||y(k) - C x^(k|k-1) - C_d d^(k|k-1)||_inf; shape (0,) without.
    setpoint_y : mapping name -> ndarray, shape (K, p_i)
        With ``estimation`` and setpoints: the outputs requested at each step, NaN where free.
    C : mapping name -> ndarray, shape (p_i, n_i)
        With ``estimation``: what the plant measures of each subsystem, y_i = C_i x_i (empty when
        the run folder has no scenario).
    outputs, disturbances : mapping name -> tuple of Quantity
        With ``estimation``: names and units of each subsystem's outputs (the scenario's
        ``outputs``) and of its disturbance estimates (``d(h1)``: the one on output or input h1).
    """

    names: tuple[str, ...]
    t: np.ndarray
    dt: float | None
    x: Mapping[str, np.ndarray]
    u: Mapping[str, np.ndarray]
    w: Mapping[str, np.ndarray]
    alpha: Mapping[str, np.ndarray]
    beta: np.ndarray
    J: np.ndarray
    cost: float
    verdict: str
    summary: dict = field(repr=False)
    design: Design | None = field(repr=False)
    states: Mapping[str, tuple[Quantity, ...]] = field(repr=False)
    inputs: Mapping[str, tuple[Quantity, ...]] = field(repr=False)
    method: str = DEFAULT_METHOD
    folder: Path | None = None
    setpoint: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    setpoint_u: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    reference: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    reference_u: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    target: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    target_u: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    governor: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    y: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    x_hat: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    d_hat: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    innovation: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    setpoint_y: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    C: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    outputs: Mapping[str, tuple[Quantity, ...]] = field(default_factory=dict, repr=False)
    disturbances: Mapping[str, tuple[Quantity, ...]] = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        where = f", folder='{self.folder}'" if self.folder is not None else ""
        dt = f", dt={self.dt:g}" if self.dt is not None else ""
        return (f"Result(verdict={self.verdict!r}, steps={self.steps}, cost={self.cost:.6g}, method={self.method!r}, "
                f"names={self.names}{dt}{where})")

    @property
    def steps(self) -> int:
        """K, the number of completed steps."""
        return int(self.J.shape[0])

    @property
    def estimated(self) -> bool:
        """The run had ``estimation``: the controllers worked from ``x_hat``, not ``x``."""
        return bool(self.x_hat)

    @property
    def time_label(self) -> str:
        """``t [s]`` or ``step k``: what ``t`` counts."""
        return time_label(self.dt)

    def stacked_x(self) -> np.ndarray:
        """The global state over time, shape (K+1, n), subsystems in order."""
        return np.hstack([self.x[name] for name in self.names])

    def stacked_u(self) -> np.ndarray:
        """The global input over time, shape (K, m)."""
        return np.hstack([self.u[name] for name in self.names])

    def table(self) -> str:
        """One line per state and input: start, end, range and bounds, as plain text. With
        ``estimation`` also one per output measured (``h1 [m] (measured)``), state estimate
        (``h3 [m] (estimate)``) and disturbance estimate (``d(h1) [m] (estimate)``)."""
        rows: list[tuple[str, ...]] = [("subsystem", "quantity", "start", "end", "min", "max", "bounds")]
        for name in self.names:
            series = [(self.x[name], self.states[name], ""), (self.u[name], self.inputs[name], "")]
            if self.estimated:
                series += [(self.y[name], self.outputs[name], " (measured)"),
                           (self.x_hat[name], self.states[name], " (estimate)"),
                           (self.d_hat[name], self.disturbances[name], " (estimate)")]
            for values, qs, what in series:
                for j, q in enumerate(qs):
                    col = values[:, j] if values.shape[0] else np.zeros(0)
                    shown = [f"{v:.4g}" for v in (col[0], col[-1], col.min(), col.max())] if col.size else [""] * 4
                    rows.append((name, q.label + what, *shown, _bounds_text(q) if not what else ""))
        widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
        text = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
        head = f"verdict {self.verdict}, {self.steps} steps, closed-loop cost {self.cost:.6g}"
        return "\n".join([head] + text)

    def plot(self, bounds: bool = True) -> dict:
        """Figures of the run: ``states``, ``inputs`` and ``cost`` (matplotlib Figures), and with
        ``estimation`` ``estimates``.

        Axes are in seconds when the scenario has ``dt``; quantities carry their names and
        units; ``bounds`` draws the state and input bounds as dashed lines. With ``estimation``
        the states figure also draws the estimates x^ (dashed) and the outputs measured that are a
        state alone (crosses), and ``estimates`` the outputs measured, the disturbance estimates and
        the innovation per step, as ``dmpc report`` does.
        """
        return plot_result(self, bounds=bounds)


def _bounds_text(q: Quantity) -> str:
    if not (np.isfinite(q.lower) or np.isfinite(q.upper)):
        return ""
    return f"[{q.lower:g}, {q.upper:g}]"


def _split(stacked: np.ndarray, names: list[str], sizes: list[int]) -> Mapping[str, np.ndarray]:
    edges = np.cumsum([0] + list(sizes))
    return MappingProxyType({name: stacked[:, edges[i]:edges[i + 1]] for i, name in enumerate(names)})


def load_run(folder, *, in_temporary_folder: bool = False) -> Result:
    """Read a finished run folder (``dmpc simulate``, ``dmpc run``, ``dmpc.simulate`` ...).

    Parameters
    ----------
    folder : path-like
    in_temporary_folder : bool
        The folder is about to be removed: the result's ``folder`` is None.

    Raises
    ------
    RunFolderNotReadable
        No ``trajectory.npz`` or ``summary.json`` (a run still going, or crashed before its end).
    """
    folder = Path(folder)
    records = read_run(folder) if is_finished_run_folder(folder) else None
    if records is None or records.summary is None:
        raise RunFolderNotReadable(f"{folder}: not a finished run folder ({TRAJECTORY} and {SUMMARY} are "
                                   "written at the end of a run)")
    names, n, m, summary = records.names, records.n, records.m, records.summary
    states, inputs = records.quantities()
    x, u = records.arrays["x"], records.arrays["u"]
    design = Design.from_json(records.design, names) if records.design else None
    tracked = tracking_arrays(records.arrays, u.shape[0], x.shape[1], u.shape[1])
    fields = _estimate_fields(records.estimates(), names, n)
    fields.update({key: _split(tracked[key], names, n if key in STATE_KEYS else m) for key in TRACKING_KEYS})
    return Result(
        names=tuple(names), t=time_axis(u.shape[0], records.dt), dt=records.dt, x=_split(x, names, n),
        u=_split(u, names, m), w=_split(records.disturbance(), names, n), alpha=_split(records.arrays["alpha"], names, n),
        beta=records.arrays["beta"], J=records.arrays["J"],
        cost=float(summary.get("closed_loop_cost", np.nan)), verdict=str(summary.get("verdict", "")),
        summary=summary, design=design, states=MappingProxyType(states), inputs=MappingProxyType(inputs),
        method=str(summary.get("method", DEFAULT_METHOD)), folder=None if in_temporary_folder else folder,
        governor=tracked["governor"], **fields)


def _estimate_fields(estimates: Estimates | None, names: list[str], n: list[int]) -> dict[str, Any]:
    """The fields of estimation of a Result (y, x_hat, d_hat, innovation, setpoint_y, C, outputs,
    disturbances) from the reader's ``estimates`` of the subsystems ``names`` with ``n`` states;
    empty without estimation."""
    if estimates is None:
        return {}
    e = estimates
    return {"y": _split(e.y, names, e.p), "x_hat": _split(e.x_hat, names, n), "d_hat": _split(e.d_hat, names, e.nd),
            "innovation": e.innovation, "setpoint_y": _split(e.setpoint_y, names, e.p),
            "C": MappingProxyType(dict(zip(names, e.C))) if e.C is not None else MappingProxyType({}),
            "outputs": MappingProxyType(dict(zip(names, e.outputs))),
            "disturbances": MappingProxyType(dict(zip(names, e.disturbances)))}
