"""Setpoint schedules: which components each subsystem is asked to reach from which step on.

Piecewise constant: for each subsystem, the latest entry at or before step k holds; a subsystem
with no entry yet asks for nothing (its components are free, see dmpc.tracking.targets). Entries
given while a run goes on join the schedule at the step they take effect.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.tracking.targets import Request


@dataclass(frozen=True, eq=False)
class SetpointEntry:
    """From step ``at`` on, subsystem ``index`` asks for ``x`` (or ``y``) and ``u`` (NaN: free).

    Attributes
    ----------
    at : int
        The first step it holds.
    index : int
        0-based subsystem index.
    x : ndarray, shape (n_i,)
    u : ndarray, shape (m_i,)
    source : str
        Where it came from: ``scenario`` or the sender of a live request.
    y : ndarray, shape (p_i,), or None
        The requested outputs y_i = C_i x_i (NaN: free), for a run with an observer (scenario
        ``estimation``), whose requests name outputs: ``x`` is then all NaN. None without one, where
        the outputs are the states and a request is in ``x``.
    """

    at: int
    index: int
    x: np.ndarray
    u: np.ndarray
    source: str = "scenario"
    y: np.ndarray | None = None


class Schedule:
    """The entries of one run, in the order they take effect.

    Parameters
    ----------
    system : CoupledSystem
    entries : iterable of SetpointEntry
        Entries with the same ``at`` and subsystem: the later one in the list holds.
    """

    def __init__(self, system: CoupledSystem, entries: Iterable[SetpointEntry] = ()) -> None:
        self.system = system
        self.entries: tuple[SetpointEntry, ...] = tuple(sorted(entries, key=lambda e: e.at))  # stable

    def __bool__(self) -> bool:
        return bool(self.entries)

    def with_entry(self, entry: SetpointEntry) -> "Schedule":
        """The schedule with ``entry`` added (after every entry of the same step)."""
        return Schedule(self.system, (*self.entries, entry))

    def request(self, k: int) -> Request:
        """The request that holds at step k."""
        system = self.system
        x = np.full(system.n, np.nan)
        u = np.full(system.m, np.nan)
        y = np.full(system.p, np.nan) if any(entry.y is not None for entry in self.entries) else None
        for entry in self.entries:
            if entry.at > k:
                break
            x[system.xs(entry.index)] = entry.x
            u[system.us(entry.index)] = entry.u
            if y is not None and entry.y is not None:
                y[system.ys(entry.index)] = entry.y
        return Request(x, u, y)

    def change_steps(self) -> list[int]:
        """The steps at which an entry takes effect, sorted, without repeats."""
        return sorted({e.at for e in self.entries})
