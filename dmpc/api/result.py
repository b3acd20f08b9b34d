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
from typing import Mapping

import numpy as np

from dmpc.core.quantities import Quantity, time_axis, time_label
from dmpc.methods import DEFAULT_METHOD
from dmpc.offline.record import Design
from dmpc.plots.result import plot_result
from dmpc.records.files import SUMMARY, TRAJECTORY
from dmpc.records.reader import (
    STATE_KEYS,
    TRACKING_KEYS,
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
        """One line per state and input: start, end, range and bounds, as plain text."""
        rows: list[tuple[str, ...]] = [("subsystem", "quantity", "start", "end", "min", "max", "bounds")]
        for name in self.names:
            for values, qs in ((self.x[name], self.states[name]), (self.u[name], self.inputs[name])):
                for j, q in enumerate(qs):
                    col = values[:, j] if values.shape[0] else np.zeros(0)
                    shown = [f"{v:.4g}" for v in (col[0], col[-1], col.min(), col.max())] if col.size else [""] * 4
                    rows.append((name, q.label, *shown, _bounds_text(q)))
        widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
        text = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
        head = f"verdict {self.verdict}, {self.steps} steps, closed-loop cost {self.cost:.6g}"
        return "\n".join([head] + text)

    def plot(self, bounds: bool = True) -> dict:
        """Figures of the run: ``states``, ``inputs`` and ``cost`` (matplotlib Figures).

        Axes are in seconds when the scenario has ``dt``; quantities carry their names and
        units; ``bounds`` draws the state and input bounds as dashed lines.
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
    return Result(
        names=tuple(names), t=time_axis(u.shape[0], records.dt), dt=records.dt, x=_split(x, names, n),
        u=_split(u, names, m), w=_split(records.disturbance(), names, n), alpha=_split(records.arrays["alpha"], names, n),
        beta=records.arrays["beta"], J=records.arrays["J"],
        cost=float(summary.get("closed_loop_cost", np.nan)), verdict=str(summary.get("verdict", "")),
        summary=summary, design=design, states=MappingProxyType(states), inputs=MappingProxyType(inputs),
        method=str(summary.get("method", DEFAULT_METHOD)), folder=None if in_temporary_folder else folder,
        governor=tracked["governor"],
        **{key: _split(tracked[key], names, n if key in STATE_KEYS else m) for key in TRACKING_KEYS})
