"""What a run's setpoints came to: the tracking error at the end per requested component, and
the requests that no admissible steady state meets (docs/algorithm.md, "Setpoints").

Pure functions of the recorded arrays: ``setpoint`` and ``reference`` (K, n), their input
counterparts (K, m), ``target`` and ``target_u`` (the targets applied), ``governor`` (K,).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.system import CoupledSystem

GAP_TOLERANCE = 1e-6
"""A requested component counts as unreachable when its target misses it by more than this times max(1, |value|)."""


@dataclass(frozen=True)
class Component:
    """One requested component: ``subsystem``, its ``label``, whether it is a state or an input
    (``kind``: ``x`` or ``u``) and where it sits in the stacked arrays (``column``)."""

    subsystem: str
    label: str
    kind: str  # "x" or "u"
    column: int


def components(system: CoupledSystem, labels: dict | None = None) -> list[Component]:
    """Every state and input component of ``system``, labelled with the scenario's names in ``labels``
    (``Ta [K]``) or x1, u1, ..."""
    labels = labels or {}
    out = []
    for i, sub in enumerate(system.subsystems):
        for kind, size, start, key in (("x", sub.n, system.xs(i).start, "state"), ("u", sub.m, system.us(i).start, "input")):
            named = labels.get(key, {}).get(sub.name)
            for c in range(size):
                out.append(Component(sub.name, named[c] if named else f"{kind}{c + 1}", kind, start + c))
    return out


def is_tracked(arrays: dict) -> bool:
    """True if something was requested during the run (the arrays hold a setpoint that is not free)."""
    return "setpoint" in arrays and bool(np.isfinite(arrays["setpoint"]).any() or np.isfinite(arrays["setpoint_u"]).any())


def _columns(arrays: dict, kind: str, name: str) -> np.ndarray:
    return arrays[name if kind == "x" else f"{name}_u"]


def unreachable(system: CoupledSystem, arrays: dict, labels: dict | None = None) -> list[dict]:
    """The requested components of ``system`` whose target misses them in the run's ``arrays``
    (labelled as :func:`components` with ``labels``): per component, the first step, the value
    asked, the nearest admissible target's value and the gap (target - asked)."""
    if not is_tracked(arrays):
        return []
    found = []
    for comp in components(system, labels):
        asked = _columns(arrays, comp.kind, "setpoint")[:, comp.column]
        got = _columns(arrays, comp.kind, "reference")[:, comp.column]
        gap = got - asked
        bad = np.flatnonzero(np.isfinite(asked) & (np.abs(gap) > GAP_TOLERANCE * np.maximum(1.0, np.abs(asked))))
        if bad.size:
            k = int(bad[0])
            found.append({"subsystem": comp.subsystem, "component": comp.label, "k": k, "asked": float(asked[k]),
                          "target": float(got[k]), "gap": float(gap[k])})
    return found


def tracking_summary(system: CoupledSystem, arrays: dict, labels: dict | None = None) -> dict | None:
    """``summary.json``'s ``tracking`` of a run of ``system`` from its ``arrays`` (components labelled
    with ``labels``): per component requested at the last step, the value asked,
    the target applied, the state reached and the error from the request; None when nothing was
    ever requested."""
    if not is_tracked(arrays):
        return None
    x, u = arrays["x"], arrays["u"]
    K = u.shape[0]
    rows: list[dict] = []
    for comp in components(system, labels):
        asked = _columns(arrays, comp.kind, "setpoint")[K - 1, comp.column]
        if not np.isfinite(asked):
            continue
        reached = x[K, comp.column] if comp.kind == "x" else u[K - 1, comp.column]
        rows.append({"subsystem": comp.subsystem, "component": comp.label, "asked": float(asked),
                     "target": float(_columns(arrays, comp.kind, "target")[K - 1, comp.column]),
                     "reference": float(_columns(arrays, comp.kind, "reference")[K - 1, comp.column]),
                     "final": float(reached), "error": float(reached - asked)})
    governed = np.flatnonzero(arrays["governor"] < 1.0)
    return {"components": rows, "max_abs_error": max((abs(r["error"]) for r in rows), default=0.0),
            "governor_steps": [int(k) for k in governed]}


def target_changes(arrays: dict) -> np.ndarray:
    """Per step k < K - 1, True where the applied target of step k+1 differs from step k's, shape
    (K-1,), from the run's ``arrays``."""
    if "target" not in arrays or arrays["target"].shape[0] < 2:
        return np.zeros(max(arrays["u"].shape[0] - 1, 0), bool)
    t = np.hstack([arrays["target"], arrays["target_u"]])
    return np.any(t[1:] != t[:-1], axis=1)
