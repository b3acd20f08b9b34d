"""What a run's setpoints came to: every segment of the schedule (per requested component and
value asked: reached or not, how fast, the error at its end), the tracking error at the end per
requested component, and the requests that no admissible steady state meets to the target
solver's accuracy (docs/algorithm.md, "Setpoints"; docs/records.md, ``tracking``).

Pure functions of the recorded arrays: ``setpoint`` and ``reference`` (K, n), their input
counterparts (K, m), ``target`` and ``target_u`` (the targets applied), ``governor`` (K,); and,
in a run with estimation whose requests name outputs (docs/algorithm.md, "Offset-free tracking"),
``setpoint_y`` (K, p). An output component is reached by the plant's own outputs, C x with the
system's C on the recorded state (noise-free), and its target is C x_s.
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
    """One requested component: ``subsystem``, its ``label``, whether it is a state, an input or an
    output (``kind``: ``x``, ``u`` or ``y``) and where it sits in the stacked arrays (``column``:
    of x (n,), u (m,) or y = C x (p,)); ``offset``, the operating point's value of it in the plant's
    units (None when the run has no operating point: the plant's units are the model's)."""

    subsystem: str
    label: str
    kind: str  # "x", "u" or "y"
    column: int
    offset: float | None = None

    def plant(self, value: float) -> float:
        """``value`` of this component (in the model's deviations) in the plant's units."""
        return float(value) if self.offset is None else float(value) + self.offset


def components(system: CoupledSystem, labels: dict | None = None, outputs: bool = False) -> list[Component]:
    """Every state and input component of ``system`` (and with ``outputs`` every output, after them),
    labelled with the scenario's names in ``labels`` (``Ta [K]``; ``labels["output"]`` for the
    outputs) or x1, u1, y1, ..."""
    labels = labels or {}
    shifted = system.has_operating_point
    out = []
    for i, sub in enumerate(system.subsystems):
        for kind, size, start, key, at in (("x", sub.n, system.xs(i).start, "state", sub.state_offset),
                                           ("u", sub.m, system.us(i).start, "input", sub.input_offset)):
            named = labels.get(key, {}).get(sub.name)
            for c in range(size):
                out.append(Component(sub.name, named[c] if named else f"{kind}{c + 1}", kind, start + c,
                                     float(at[c]) if shifted else None))
    if outputs:
        for i, sub in enumerate(system.subsystems):
            named = labels.get("output", {}).get(sub.name)
            start = system.ys(i).start
            at = sub.operating_output
            for c in range(sub.p):
                out.append(Component(sub.name, named[c] if named else f"y{c + 1}", "y", start + c,
                                     float(at[c]) if shifted else None))
    return out


def has_outputs(arrays: dict) -> bool:
    """True if the run whose ``arrays`` these are requested outputs (``setpoint_y`` holds a value that
    is not free)."""
    return "setpoint_y" in arrays and bool(np.isfinite(arrays["setpoint_y"]).any())


def is_tracked(arrays: dict) -> bool:
    """True if something was requested during the run (the arrays hold a setpoint that is not free:
    of a state, an input or an output)."""
    return "setpoint" in arrays and bool(np.isfinite(arrays["setpoint"]).any() or np.isfinite(arrays["setpoint_u"]).any()
                                         or has_outputs(arrays))


def _columns(arrays: dict, kind: str, name: str) -> np.ndarray:
    return arrays[name if kind == "x" else f"{name}_u"]


def outputs_of(system: CoupledSystem, states: np.ndarray) -> np.ndarray:
    """The outputs C x of ``states`` (x (n,), or rows of x (K, n)) with the measurement matrix C of
    ``system``, block by block (C_i x_i): (p,) or (K, p)."""
    states = np.asarray(states, float)
    out = np.empty(states.shape[:-1] + (system.p,))
    for i, sub in enumerate(system.subsystems):
        out[..., system.ys(i)] = states[..., system.xs(i)] @ sub.output_matrix.T
    return out


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


def _requests(system: CoupledSystem, arrays: dict) -> tuple[np.ndarray, np.ndarray]:
    """The requests and their targets per step, stacked [x, u]: (K, n + m) each; [x, u, y] (K, n + m
    + p) in a run that requested outputs (the target of an output: C x_s)."""
    asked = [arrays["setpoint"], arrays["setpoint_u"]]
    got = [arrays["reference"], arrays["reference_u"]]
    if has_outputs(arrays):
        asked.append(arrays["setpoint_y"])
        got.append(outputs_of(system, arrays["reference"]))
    return np.hstack(asked), np.hstack(got)


def _tolerances(system: CoupledSystem, asked: np.ndarray, margin: float) -> np.ndarray:
    """:func:`gap_tolerance` of every step's request ``asked`` (K, n + m), computed once per request;
    an output's (the columns after n + m) is ``GAP_TOLERANCE`` max(1, |a|): its target comes from
    the offset-free targets' linear solve, not from the steady-state QP."""
    out = np.empty_like(asked)
    n, m = system.n, system.m
    for k in range(asked.shape[0]):
        if k and np.array_equal(asked[k], asked[k - 1], equal_nan=True):
            out[k] = out[k - 1]
        else:
            out[k, :n + m] = gap_tolerance(asked[k, :n], asked[k, n:n + m], system, margin)
            out[k, n + m:] = GAP_TOLERANCE * np.maximum(1.0, np.abs(np.nan_to_num(asked[k, n + m:])))
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


def _stacked_components(system: CoupledSystem, labels: dict | None,
                        outputs: bool = False) -> list[tuple[Component, int]]:
    """Every component of ``system`` (:func:`components`, labelled with ``labels``, the outputs too
    with ``outputs``) with its column in the stacked [x, u] (or [x, u, y]) arrays."""
    offset = {"x": 0, "u": system.n, "y": system.n + system.m}
    return [(c, offset[c.kind] + c.column) for c in components(system, labels, outputs)]


def unreachable(system: CoupledSystem, arrays: dict, labels: dict | None = None,
                margin: float = DEFAULT_MARGIN) -> list[dict]:
    """The requests in a run of ``system`` (its ``arrays``) that no admissible steady state meets: per
    requested component and value asked (each segment of the schedule, :func:`segments`), the first
    step where its target missed it by more than the solver's accuracy (:func:`gap_tolerance` with
    ``margin``), the value asked, the target's value and the gap (target - asked). Components are
    labelled as :func:`components` with ``labels``. Requested outputs are not judged here: their
    target C x_s moves with the disturbance estimate (:func:`segments`).
    """
    if not is_tracked(arrays):
        return []
    asked, got = _requests(system, arrays)
    tolerance = _tolerances(system, asked, margin)
    found = []
    for comp, col in _stacked_components(system, labels):  # an output's target moves with the disturbance
        gap = got[:, col] - asked[:, col]
        for start, until in _segments_of(asked[:, col]):
            bad = np.flatnonzero(np.abs(gap[start:until]) > tolerance[start:until, col])
            if bad.size:
                k = start + int(bad[0])
                found.append({"subsystem": comp.subsystem, "component": comp.label, "k": k,
                              "asked": comp.plant(asked[k, col]), "target": comp.plant(got[k, col]),
                              "gap": float(gap[k])})
    return sorted(found, key=lambda g: g["k"])


def _settling(values: np.ndarray, asked: float, band: float) -> int | None:
    """The first index of ``values`` from which every value is within ``band`` of ``asked``; None
    when the last one is not."""
    outside = np.flatnonzero(~(np.abs(values - asked) <= band))
    if not outside.size:
        return 0
    last = int(outside[-1])
    return None if last == values.size - 1 else last + 1


@dataclass(frozen=True, eq=False)
class SegmentTrace:
    """One segment of :func:`segments` with what the verdict's ``offset`` check needs beyond it.

    Attributes
    ----------
    entry : dict
        The segment as ``tracking.segments`` has it.
    errors : ndarray
        The component minus the value asked over the segment: x(at) .. x(until) for a state (and
        C x for an output), u(at) .. u(until - 1) for an input.
    accuracy : float
        The error the targets themselves explain: the request's target's own gap from the value
        asked (|target - asked| at the segment's last step) plus ``GAP_TOLERANCE`` max(1, |asked|);
        for an output only the latter (its target C x_s moves with the disturbance estimate).
    held : float
        |applied target - request's target| in the component at the segment's last step: what the
        reference governor still held back there.
    """

    entry: dict
    errors: np.ndarray
    accuracy: float
    held: float


def segment_traces(system: CoupledSystem, arrays: dict, labels: dict | None = None, dt: float | None = None,
                   margin: float = DEFAULT_MARGIN) -> list[SegmentTrace]:
    """Every segment of the run (:func:`segments`, same parameters) with its errors over the segment,
    the accuracy of its target and what the governor held back at its end (:class:`SegmentTrace`), in
    order of ``at``.

    Parameters
    ----------
    system : CoupledSystem
    arrays : dict
        The run's arrays (``x``, ``u`` and the setpoint arrays; ``setpoint_y`` in a run that
        requested outputs).
    labels : dict, optional
        The scenario's labels, as :func:`components` takes them.
    dt : float, optional
        The seconds per step.
    margin : float
        The setpoint margin the targets keep.
    """
    if not is_tracked(arrays):
        return []
    outputs = has_outputs(arrays)
    asked, got = _requests(system, arrays)
    tolerance = _tolerances(system, asked, margin)
    x, u = arrays["x"], arrays["u"]
    applied = np.hstack([arrays["target"], arrays["target_u"]]
                        + ([outputs_of(system, arrays["target"])] if outputs else []))
    y = outputs_of(system, x) if outputs else None
    found = []
    for comp, col in _stacked_components(system, labels, outputs):
        for start, until in _segments_of(asked[:, col]):
            a = float(asked[start, col])
            if comp.kind == "u":
                values = u[start: until, comp.column]
                before = float(u[start - 1, comp.column]) if start else 0.0
            else:
                values = (y if comp.kind == "y" and y is not None else x)[start: until + 1, comp.column]
                before = float(values[0])
            step = a - before
            band = max(SETTLING_FRACTION * abs(step), float(tolerance[until - 1, col]))
            error = float(values[-1]) - a
            settled = _settling(values, a, band)
            target = float(got[until - 1, col])
            floor = GAP_TOLERANCE * max(1.0, abs(a))
            entry = {"at": start, "until": until, "subsystem": comp.subsystem, "component": comp.label,
                     "asked": comp.plant(a), "target": comp.plant(target),
                     "reachable": (None if comp.kind == "y" else bool(abs(target - a) <= tolerance[until - 1, col])),
                     "step": step, "tolerance": band, "reached": bool(abs(error) <= band),
                     "settling_steps": settled, "settling_s": settled * dt if settled is not None and dt else None,
                     "error_at_end": error}
            if comp.kind == "y":
                entry["output"] = True
            found.append(SegmentTrace(entry, np.asarray(values, float) - a,
                                      floor if comp.kind == "y" else abs(target - a) + floor,
                                      abs(float(applied[until - 1, col]) - target)))
    return sorted(found, key=lambda t: t.entry["at"])


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

    An output (a run with estimation whose requests name outputs) has ``output`` true, its values
    are the plant's outputs C x (the system's C on the recorded state, no measurement noise), its
    ``target`` is C x_s of the request's target and ``reachable`` is None: that target moves with
    the disturbance estimate, so it is not compared with the value asked.
    """
    return [trace.entry for trace in segment_traces(system, arrays, labels, dt, margin)]


def tracking_summary(system: CoupledSystem, arrays: dict, labels: dict | None = None, dt: float | None = None,
                     margin: float = DEFAULT_MARGIN, traces: list[SegmentTrace] | None = None) -> dict | None:
    """``summary.json``'s ``tracking`` of a run of ``system`` from its ``arrays`` (components labelled
    with ``labels``): per component requested at the last step, the value asked,
    the target applied, the state reached and the error from the request; every segment of the
    schedule (:func:`segments`, settling times in seconds with ``dt``, reachability with the setpoint
    ``margin``; ``traces``, :func:`segment_traces` of the same arguments, when already computed);
    ``dt`` itself; None when nothing was ever requested.

    An output requested at the last step (a run with estimation) has ``final`` = C x(K), ``target``
    and ``reference`` C x_s of the target applied and of the request's.
    """
    if not is_tracked(arrays):
        return None
    x, u = arrays["x"], arrays["u"]
    K = u.shape[0]
    outputs = has_outputs(arrays)
    rows: list[dict] = []
    for comp in components(system, labels, outputs):
        if comp.kind == "y":
            asked = arrays["setpoint_y"][K - 1, comp.column]
            if not np.isfinite(asked):
                continue
            reached = float(outputs_of(system, x[K])[comp.column])
            target = float(outputs_of(system, arrays["target"][K - 1])[comp.column])
            reference = float(outputs_of(system, arrays["reference"][K - 1])[comp.column])
        else:
            asked = _columns(arrays, comp.kind, "setpoint")[K - 1, comp.column]
            if not np.isfinite(asked):
                continue
            reached = x[K, comp.column] if comp.kind == "x" else u[K - 1, comp.column]
            target = float(_columns(arrays, comp.kind, "target")[K - 1, comp.column])
            reference = float(_columns(arrays, comp.kind, "reference")[K - 1, comp.column])
        rows.append({"subsystem": comp.subsystem, "component": comp.label, "asked": comp.plant(asked),
                     "target": comp.plant(target), "reference": comp.plant(reference), "final": comp.plant(reached),
                     "error": float(reached - asked), **({"output": True} if comp.kind == "y" else {})})
    governed = np.flatnonzero(arrays["governor"] < 1.0)
    if traces is None:
        traces = segment_traces(system, arrays, labels, dt, margin)
    return {"components": rows, "max_abs_error": max((abs(r["error"]) for r in rows), default=0.0),
            "governor_steps": [int(k) for k in governed], "dt": dt,
            "segments": [trace.entry for trace in traces]}


def target_changes(arrays: dict) -> np.ndarray:
    """Per step k < K - 1, True where the applied target of step k+1 differs from step k's, shape
    (K-1,), from the run's ``arrays``."""
    if "target" not in arrays or arrays["target"].shape[0] < 2:
        return np.zeros(max(arrays["u"].shape[0] - 1, 0), bool)
    t = np.hstack([arrays["target"], arrays["target_u"]])
    return np.any(t[1:] != t[:-1], axis=1)
