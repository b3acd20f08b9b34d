"""What a run's setpoints came to: every segment of the schedule (per requested component and
value asked: reached or not, how fast, the error at its end), the tracking error at the end per
requested component, and the requests that no admissible steady state meets to the target
solver's accuracy (docs/algorithm.md, "Setpoints"; docs/records.md, ``tracking``).

Pure functions of the recorded arrays: ``setpoint`` and ``reference`` (K, n), their input
counterparts (K, m), ``target`` and ``target_u`` (the targets applied), ``governor`` (K,).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.tracking.targets import DEFAULT_MARGIN, MARGIN_ROOM, SOLVER_TOLERANCE

GAP_TOLERANCE = 1e-6
"""Part of :func:`gap_tolerance`: what the targets' second stage and regularisation may move a met
component, relative to max(1, |value|)."""
SETTLING_FRACTION = 0.02
"""A segment's component has settled once it stays within this fraction of its step of the value
asked (the 2 % settling time)."""


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


def weights(system: CoupledSystem) -> np.ndarray:
    """The weight of each component of ``system`` in the nearest-target QP
    (:meth:`~dmpc.tracking.targets.TargetSpace.target`), in the order of the stacked [x, u]: the
    diagonals of Q and R, 1 where zero, (n + m,)."""
    d = np.concatenate([np.diag(s.Q) for s in system.subsystems] + [np.diag(s.R) for s in system.subsystems])
    return np.where(d > 0, d, 1.0).astype(float)


def gap_tolerance(asked_x: np.ndarray, asked_u: np.ndarray, system: CoupledSystem,
                  margin: float = DEFAULT_MARGIN) -> np.ndarray:
    """The largest gap between a request and its target that is the target solver's accuracy, per
    component of the stacked [x, u] (n + m,).

    The nearest admissible target minimises sum_c w_c (w_c - a_c)^2 over the requested components
    (weights :func:`weights`); the solver settles that objective to ``SOLVER_TOLERANCE`` times
    max(1, S), S = sum_c w_c a_c^2, so a component misses by up to sqrt(SOLVER_TOLERANCE max(1, S) / w_c)
    where the request can be met. A target also keeps ``MARGIN_ROOM`` further inside than the
    margin: |a_c| MARGIN_ROOM / (1 - margin) for a request on the margin. Then ``GAP_TOLERANCE``
    max(1, |a_c|) for the second stage. A request exactly on the margin (gauge 1 - margin) is met
    within the sum, one beyond it by more is not.

    Parameters
    ----------
    asked_x : ndarray, shape (n,)
        The request's state components, NaN where free.
    asked_u : ndarray, shape (m,)
        Its input components, NaN where free.
    system : CoupledSystem
    margin : float
        The setpoint margin the targets keep (``options.setpoint_margin``).
    """
    asked = np.abs(np.nan_to_num(np.concatenate([asked_x, asked_u])))
    w = weights(system)
    size = max(1.0, float(np.sum(w * asked ** 2)))
    return (np.sqrt(SOLVER_TOLERANCE * size / w) + asked * MARGIN_ROOM / (1.0 - margin)
            + GAP_TOLERANCE * np.maximum(1.0, asked))


def _requests(arrays: dict) -> tuple[np.ndarray, np.ndarray]:
    """The requests and their targets per step, stacked [x, u]: (K, n + m) each."""
    return (np.hstack([arrays["setpoint"], arrays["setpoint_u"]]),
            np.hstack([arrays["reference"], arrays["reference_u"]]))


def _tolerances(system: CoupledSystem, asked: np.ndarray, margin: float) -> np.ndarray:
    """:func:`gap_tolerance` of every step's request ``asked`` (K, n + m), computed once per request."""
    out = np.empty_like(asked)
    n = system.n
    for k in range(asked.shape[0]):
        if k and np.array_equal(asked[k], asked[k - 1], equal_nan=True):
            out[k] = out[k - 1]
        else:
            out[k] = gap_tolerance(asked[k, :n], asked[k, n:], system, margin)
    return out


def _segments_of(asked: np.ndarray) -> list[tuple[int, int]]:
    """The runs [start, until) of steps over which one component's request ``asked`` (K,) holds
    the same value (free steps, NaN, belong to none)."""
    K = asked.shape[0]
    if K == 0:
        return []
    change = np.flatnonzero(~((asked[1:] == asked[:-1]) | (np.isnan(asked[1:]) & np.isnan(asked[:-1])))) + 1
    bounds = [0, *change.tolist(), K]
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if np.isfinite(asked[a])]


def _stacked_components(system: CoupledSystem, labels: dict | None) -> list[tuple[Component, int]]:
    """Every component of ``system`` (:func:`components`, labelled with ``labels``) with its column in
    the stacked [x, u] arrays."""
    return [(c, c.column if c.kind == "x" else system.n + c.column) for c in components(system, labels)]


def unreachable(system: CoupledSystem, arrays: dict, labels: dict | None = None,
                margin: float = DEFAULT_MARGIN) -> list[dict]:
    """The requests in a run of ``system`` (its ``arrays``) that no admissible steady state meets: per
    requested component and value asked (each segment of the schedule, :func:`segments`), the first
    step where its target missed it by more than the solver's accuracy (:func:`gap_tolerance` with
    ``margin``), the value asked, the target's value and the gap (target - asked). Components are
    labelled as :func:`components` with ``labels``.
    """
    if not is_tracked(arrays):
        return []
    asked, got = _requests(arrays)
    tolerance = _tolerances(system, asked, margin)
    found = []
    for comp, col in _stacked_components(system, labels):
        gap = got[:, col] - asked[:, col]
        for start, until in _segments_of(asked[:, col]):
            bad = np.flatnonzero(np.abs(gap[start:until]) > tolerance[start:until, col])
            if bad.size:
                k = start + int(bad[0])
                found.append({"subsystem": comp.subsystem, "component": comp.label, "k": k,
                              "asked": float(asked[k, col]), "target": float(got[k, col]), "gap": float(gap[k])})
    return sorted(found, key=lambda g: g["k"])


def _settling(values: np.ndarray, asked: float, band: float) -> int | None:
    """The first index of ``values`` from which every value is within ``band`` of ``asked``; None
    when the last one is not."""
    outside = np.flatnonzero(~(np.abs(values - asked) <= band))
    if not outside.size:
        return 0
    last = int(outside[-1])
    return None if last == values.size - 1 else last + 1


def segments(system: CoupledSystem, arrays: dict, labels: dict | None = None, dt: float | None = None,
             margin: float = DEFAULT_MARGIN) -> list[dict]:
    """``summary.json``'s ``tracking.segments`` of a run of ``system`` from its ``arrays``: one entry per
    requested component and value asked (a segment: the steps ``at`` to ``until`` - 1 over which the
    value holds), in order of ``at``.

    Each has ``subsystem``, ``component`` (labelled with ``labels``), ``asked``, ``target`` (the
    request's target at the segment's last step), ``reachable`` (the target meets the request to
    the solver's accuracy, :func:`gap_tolerance` with ``margin``), ``step`` (asked minus the value
    at ``at``: x(at), or u(at - 1) for an input, 0 before the first step), ``tolerance`` (the larger
    of ``SETTLING_FRACTION`` |step| and that accuracy), ``reached`` (|error_at_end| <= tolerance),
    ``settling_steps`` (steps after ``at`` from which the component stays within the tolerance of
    the value asked until the segment ends; None when it is not there at the end), ``settling_s``
    (settling_steps dt, None without ``dt``) and ``error_at_end`` (x(until), or u(until - 1), minus asked).
    """
    if not is_tracked(arrays):
        return []
    asked, got = _requests(arrays)
    tolerance = _tolerances(system, asked, margin)
    x, u = arrays["x"], arrays["u"]
    found = []
    for comp, col in _stacked_components(system, labels):
        for start, until in _segments_of(asked[:, col]):
            a = float(asked[start, col])
            if comp.kind == "x":
                values = x[start: until + 1, comp.column]
                before = float(values[0])
            else:
                values = u[start: until, comp.column]
                before = float(u[start - 1, comp.column]) if start else 0.0
            step = a - before
            band = max(SETTLING_FRACTION * abs(step), float(tolerance[until - 1, col]))
            error = float(values[-1]) - a
            settled = _settling(values, a, band)
            target = float(got[until - 1, col])
            found.append({"at": start, "until": until, "subsystem": comp.subsystem, "component": comp.label,
                          "asked": a, "target": target,
                          "reachable": bool(abs(target - a) <= tolerance[until - 1, col]), "step": step,
                          "tolerance": band, "reached": bool(abs(error) <= band), "settling_steps": settled,
                          "settling_s": settled * dt if settled is not None and dt else None,
                          "error_at_end": error})
    return sorted(found, key=lambda s: s["at"])


def tracking_summary(system: CoupledSystem, arrays: dict, labels: dict | None = None, dt: float | None = None,
                     margin: float = DEFAULT_MARGIN) -> dict | None:
    """``summary.json``'s ``tracking`` of a run of ``system`` from its ``arrays`` (components labelled
    with ``labels``): per component requested at the last step, the value asked,
    the target applied, the state reached and the error from the request; every segment of the
    schedule (:func:`segments`, settling times in seconds with ``dt``, reachability with the setpoint
    ``margin``); ``dt`` itself; None when nothing was ever requested."""
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
            "governor_steps": [int(k) for k in governed], "dt": dt,
            "segments": segments(system, arrays, labels, dt, margin)}


def target_changes(arrays: dict) -> np.ndarray:
    """Per step k < K - 1, True where the applied target of step k+1 differs from step k's, shape
    (K-1,), from the run's ``arrays``."""
    if "target" not in arrays or arrays["target"].shape[0] < 2:
        return np.zeros(max(arrays["u"].shape[0] - 1, 0), bool)
    t = np.hstack([arrays["target"], arrays["target_u"]])
    return np.any(t[1:] != t[:-1], axis=1)
