"""The result of a run, read from its run folder and indexed by subsystem name (``dmpc.Result``).

``dmpc.simulate`` and ``dmpc.run`` write a run folder and return :func:`load_run` of it, so a
result read back later is the same. Older run folders (whose ``trajectory.npz`` has no names
and sizes) are split with the sizes of their ``scenario.yaml`` or ``design.json``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

import numpy as np

from dmpc.offline_design import Design
from dmpc.records.files import DESIGN, DISTURBANCE, SCENARIO, SUMMARY, TRAJECTORY
from dmpc.quantities import Quantity, default_quantities, quantities
from dmpc.result_plots import plot_result
from dmpc.scenario import load_scenario


class RunFolderNotReadable(ValueError):
    """The folder is not a finished run folder (no trajectory.npz or summary.json)."""


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
    method: str = "tv-box"
    folder: Path | None = None

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
        return "t [s]" if self.dt is not None else "step k"

    def stacked_x(self) -> np.ndarray:
        """The global state over time, shape (K+1, n), subsystems in order."""
        return np.hstack([self.x[name] for name in self.names])

    def stacked_u(self) -> np.ndarray:
        """The global input over time, shape (K, m)."""
        return np.hstack([self.u[name] for name in self.names])

    def table(self) -> str:
        """One line per state and input: start, end, range and bounds, as plain text."""
        rows = [("subsystem", "quantity", "start", "end", "min", "max", "bounds")]
        for name in self.names:
            for kind, values, qs in (("x", self.x[name], self.states[name]), ("u", self.u[name], self.inputs[name])):
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


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _scenario(folder: Path):
    try:
        return load_scenario(folder / SCENARIO)
    except Exception:  # noqa: BLE001 - an older or hand-edited scenario: the arrays still load
        return None


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
    summary = _read_json(folder / SUMMARY)
    if not (folder / TRAJECTORY).is_file() or summary is None:
        raise RunFolderNotReadable(f"{folder}: not a finished run folder ({TRAJECTORY} and {SUMMARY} are "
                                   "written at the end of a run)")
    with np.load(folder / TRAJECTORY, allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    design_data = _read_json(folder / DESIGN) or {}
    scenario = _scenario(folder)
    names, n, m = _layout(arrays, scenario, design_data)
    if scenario is not None:
        states, inputs = quantities(scenario)
        dt = scenario.dt
    else:
        states, inputs = default_quantities(names, n, "x"), default_quantities(names, m, "u")
        dt = None
    x, u = arrays["x"], arrays["u"]
    K = u.shape[0]
    w = np.zeros((K, x.shape[1]))
    if (folder / DISTURBANCE).is_file():
        drawn = np.load(folder / DISTURBANCE, allow_pickle=False)
        w[:min(K, drawn.shape[0])] = drawn[:K]
    t = np.arange(K + 1, dtype=float) * (dt if dt is not None else 1.0)
    design = Design.from_json(design_data, names) if design_data else None
    return Result(
        names=tuple(names), t=t, dt=dt, x=_split(x, names, n), u=_split(u, names, m), w=_split(w, names, n),
        alpha=_split(arrays["alpha"], names, n), beta=arrays["beta"], J=arrays["J"],
        cost=float(summary.get("closed_loop_cost", np.nan)), verdict=str(summary.get("verdict", "")),
        summary=summary, design=design, states=MappingProxyType(states), inputs=MappingProxyType(inputs),
        method=str(summary.get("method", "tv-box")), folder=None if in_temporary_folder else folder)


def _layout(arrays: dict, scenario, design_data: dict) -> tuple[list[str], list[int], list[int]]:
    """Subsystem names and state and input sizes: from the arrays, else the scenario, else the design."""
    if "names" in arrays:
        return ([str(v) for v in arrays["names"]], [int(v) for v in arrays["state_sizes"]],
                [int(v) for v in arrays["input_sizes"]])
    if scenario is not None:
        subs = scenario.resolved_subsystems()
        return [s.name for s in subs], [s.n for s in subs], [s.m for s in subs]
    if design_data.get("K"):
        shapes = [np.asarray(k).shape for k in design_data["K"]]
        return [str(i + 1) for i in range(len(shapes))], [s[1] for s in shapes], [s[0] for s in shapes]
    return ["system"], [arrays["x"].shape[1]], [arrays["u"].shape[1]]
