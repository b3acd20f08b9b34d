"""Names, units and bounds of each subsystem's states and inputs (``states:``/``inputs:`` in a scenario),
and the time axis of a run.

Used by results, their tables, their figures (``result.plot()`` and ``dmpc report``) and the
verdict's messages: the one place where a quantity's label (``Ta [K]``) and the time axis
(``t [s]`` with the scenario's ``dt``, else ``step k``) are made. A quantity without a name in
the scenario is called ``x1, x2, ...`` (states) or ``u1, u2, ...`` (inputs); bounds come from
box sets only (a polytope has no per-coordinate bounds: they are infinite here).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Quantity:
    """One state or input component.

    Attributes
    ----------
    name : str
    unit : str
        Empty for none.
    lower, upper : float
        Its bounds (infinite for none).
    """

    name: str
    unit: str = ""
    lower: float = -np.inf
    upper: float = np.inf

    @property
    def label(self) -> str:
        """``name [unit]``, or the name alone."""
        return f"{self.name} [{self.unit}]" if self.unit else self.name


def time_label(dt: float | None) -> str:
    """``t [s]`` when the scenario has a sampling period ``dt``, else ``step k``."""
    return "t [s]" if dt is not None else "step k"


def time_axis(steps: int, dt: float | None) -> np.ndarray:
    """The time of x(0) .. x(steps), shape (steps + 1,): seconds k dt with ``dt``, else k."""
    return np.arange(steps + 1, dtype=float) * (dt if dt is not None else 1.0)


class Labelled(Protocol):
    """A scenario's name and unit of one quantity (a ``dmpc.scenario.LabelSpec``)."""

    @property
    def name(self) -> str: ...

    @property
    def unit(self) -> str: ...


class SubsystemQuantities(Protocol):
    """What is read here of a scenario's subsystem (a ``dmpc.scenario.SubsystemSpec``): its name,
    sizes, labels and sets."""

    @property
    def name(self) -> str: ...

    @property
    def n(self) -> int: ...

    @property
    def m(self) -> int: ...

    @property
    def states(self) -> Sequence[Labelled] | None: ...

    @property
    def inputs(self) -> Sequence[Labelled] | None: ...

    @property
    def state(self) -> object: ...

    @property
    def input(self) -> object: ...


class ScenarioQuantities(Protocol):
    """What is read here of a scenario (a ``dmpc.scenario.Scenario``): its subsystems."""

    def resolved_subsystems(self) -> Sequence[SubsystemQuantities]: ...


def _box(spec: object, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-coordinate bounds of a scenario set (a BoxSpec), infinite for a polytope or none."""
    if spec is not None and hasattr(spec, "lower") and hasattr(spec, "upper"):  # a BoxSpec has both
        return np.asarray(spec.lower, float), np.asarray(spec.upper, float)
    return np.full(dim, -np.inf), np.full(dim, np.inf)


def quantities(scenario: ScenarioQuantities) -> tuple[dict[str, tuple[Quantity, ...]], dict[str, tuple[Quantity, ...]]]:
    """The states and inputs of every subsystem of a scenario, by subsystem name.

    Parameters
    ----------
    scenario : dmpc.scenario.Scenario

    Returns
    -------
    states : dict name -> tuple of Quantity (n_i entries)
    inputs : dict name -> tuple of Quantity (m_i entries)
    """
    states: dict[str, tuple[Quantity, ...]] = {}
    inputs: dict[str, tuple[Quantity, ...]] = {}
    for sub in scenario.resolved_subsystems():
        states[sub.name] = _listed(sub.states, "x", *_box(sub.state, sub.n))
        inputs[sub.name] = _listed(sub.inputs, "u", *_box(sub.input, sub.m))
    return states, inputs


def named_labels(scenario: ScenarioQuantities) -> dict[str, dict[str, tuple[str, ...]]]:
    """The labels (``Ta [K]``) of the quantities a scenario names: ``{"state": {subsystem: labels},
    "input": {...}}``, only for the subsystems whose ``states:`` / ``inputs:`` are given (for
    messages that otherwise say ``component x1``)."""
    states, inputs = quantities(scenario)
    out: dict[str, dict[str, tuple[str, ...]]] = {"state": {}, "input": {}}
    for sub in scenario.resolved_subsystems():
        if sub.states:
            out["state"][sub.name] = tuple(q.label for q in states[sub.name])
        if sub.inputs:
            out["input"][sub.name] = tuple(q.label for q in inputs[sub.name])
    return out


def default_quantities(names: list[str], sizes: list[int], prefix: str) -> dict[str, tuple[Quantity, ...]]:
    """Unnamed, unbounded quantities (``x1, x2, ...`` with ``prefix`` ``x``) for runs whose scenario
    cannot be read: for each of ``names``, as many as its entry of ``sizes``."""
    return {name: tuple(Quantity(f"{prefix}{j + 1}") for j in range(size)) for name, size in zip(names, sizes)}


def run_quantities(scenario: ScenarioQuantities | None, names: list[str], n: list[int],
                   m: list[int]) -> tuple[dict[str, tuple[Quantity, ...]], dict[str, tuple[Quantity, ...]]]:
    """:func:`quantities` of a run's scenario, or unnamed ones of the given sizes without one
    (``scenario`` None): subsystem ``names`` with n[i] states and m[i] inputs."""
    if scenario is not None:
        return quantities(scenario)
    return default_quantities(names, n, "x"), default_quantities(names, m, "u")


def _listed(labels: Sequence[Labelled] | None, prefix: str, lower: np.ndarray,
            upper: np.ndarray) -> tuple[Quantity, ...]:
    out = []
    for j in range(lower.size):
        name, unit = (labels[j].name, labels[j].unit) if labels else (f"{prefix}{j + 1}", "")
        out.append(Quantity(name, unit, float(lower[j]), float(upper[j])))
    return tuple(out)
