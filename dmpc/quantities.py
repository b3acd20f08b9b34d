"""Names, units and bounds of each subsystem's states and inputs (``states:``/``inputs:`` in a scenario).

Used by results, their tables and their figures. A quantity without a name in the scenario is
called ``x1, x2, ...`` (states) or ``u1, u2, ...`` (inputs); bounds come from box sets only
(a polytope has no per-coordinate bounds: they are infinite here).
"""
from __future__ import annotations

from dataclasses import dataclass

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


def _box(spec, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-coordinate bounds of a scenario set (a BoxSpec), infinite for a polytope or none."""
    if spec is not None and hasattr(spec, "lower"):
        return np.asarray(spec.lower, float), np.asarray(spec.upper, float)
    return np.full(dim, -np.inf), np.full(dim, np.inf)


def quantities(scenario) -> tuple[dict[str, tuple[Quantity, ...]], dict[str, tuple[Quantity, ...]]]:
    """The states and inputs of every subsystem of a scenario, by subsystem name.

    Parameters
    ----------
    scenario : dmpc.scenario.Scenario

    Returns
    -------
    states : dict name -> tuple of Quantity (n_i entries)
    inputs : dict name -> tuple of Quantity (m_i entries)
    """
    states, inputs = {}, {}
    for sub in scenario.resolved_subsystems():
        states[sub.name] = _listed(sub.states, "x", *_box(sub.state, sub.n))
        inputs[sub.name] = _listed(sub.inputs, "u", *_box(sub.input, sub.m))
    return states, inputs


def default_quantities(names: list[str], sizes: list[int], prefix: str) -> dict[str, tuple[Quantity, ...]]:
    """Unnamed, unbounded quantities (``x1, x2, ...``) for runs whose scenario cannot be read."""
    return {name: tuple(Quantity(f"{prefix}{j + 1}") for j in range(size)) for name, size in zip(names, sizes)}


def _listed(labels, prefix: str, lower: np.ndarray, upper: np.ndarray) -> tuple[Quantity, ...]:
    out = []
    for j in range(lower.size):
        name, unit = (labels[j].name, labels[j].unit) if labels else (f"{prefix}{j + 1}", "")
        out.append(Quantity(name, unit, float(lower[j]), float(upper[j])))
    return tuple(out)
