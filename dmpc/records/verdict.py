"""The verdict of a run: ``ok``, or the failures found, each with where and how much.

A pure function of the system and the recorded arrays (no I/O). Failures make a run ``failed``
(exit code 3 of ``dmpc simulate`` and ``dmpc run``); warnings are reported but do not:

========================  ========  ==============================================================
kind                      class     when
========================  ========  ==============================================================
``state-violated``        failure   a state left X_i by more than ``BOUND_TOL`` (per subsystem)
``input-violated``        failure   an applied input left U_i by more than ``BOUND_TOL``
``infeasible-start``      failure   no feasible plan at k = 0 (a QP failed there; the message says
                                    why the centralised QP gave no plan to start from either)
``infeasible``            failure   steps k > 0 where an agent's QP failed (fallback applied)
``diverged``              failure   a non-finite state, or ||x(k)||_inf > ``DIVERGENCE_FACTOR``
                                    times the reference size (below)
``incomplete``            failure   fewer steps recorded than planned (stopped or interrupted)
``fallbacks``             warning   plans missed or lost (expected under injected faults)
``not-converged``         warning   ||x(end)||_inf > ``CONVERGED_FRACTION`` * ||x(0)||_inf (with
                                    setpoints: see below)
``jacobi-cap``            warning   a Jacobi iteration stopped at its cap before its tolerance
``inputs-refused``        warning   the plant refused plans whose inputs left U_i
``setpoint-unreachable``  warning   no admissible steady state meets a requested value: the
                                    nearest one was tracked (the message names the gap); one per
                                    component and value asked
``offset``                warning   a tracked component (state, output or input) settled off the
                                    value asked at the end of its setpoint segment (below)
``estimator-diverging``   warning   with estimation: the innovation kept growing (below)
``estimation-margin``     warning   with ``estimation.margin``: the estimation error |x - x^| of a
                                    state exceeded the margin kept for it (per subsystem), so the
                                    state bounds were not guaranteed at those steps
========================  ========  ==============================================================

With setpoints, ``not-converged`` measures the final state from the target applied at the last
step against the largest setpoint step (||x(0) - x_s(0)||_inf and every change of the request's
target, :func:`setpoint_step`), not against a start that may sit on its target, and also says when
the target applied had not reached the request's yet. A request's gap counts once it exceeds the
target solver's accuracy (:func:`dmpc.records.tracking.gap_tolerance`): a request exactly on the
setpoint margin is met.

A run whose requests name outputs (with estimation: ``setpoint_y``) is judged on the outputs
instead: ``not-converged`` when a requested output's C x(end) (or a requested input's u(end)) is
further from the value asked than ``CONVERGED_FRACTION`` times the largest setpoint step, the
largest |step| of its segments (:func:`dmpc.records.tracking.segments`: the change of the value
asked, the first one from the initial output); the unmeasured states have no setpoint, and under
a model mismatch their steady state is not the model's target.

``offset``: per setpoint segment and tracked component, |error_at_end| (the segment's, in
``tracking.segments``) above ``OFFSET_FRACTION`` times |step| (the change of the value asked at the
segment's start, from the initial value for the first), and above what the target itself explains
(its own gap from the value asked, plus 1e-6 max(1, |asked|)), while the error has *settled*: over
the segment's last ``SETTLED_TAIL`` of its values (at least ``SETTLED_VALUES``, at most all) it
stays within ``SETTLED_CHANGE`` of its value at the end. At that pace the error would need about
the segment's whole length again to go, so within the segment it is an offset, not a slow
approach; an error still moving by more (a slow loop, noise, a disturbance that varies) is not
reported. A segment whose request has no admissible steady state (``setpoint-unreachable`` says
so), or whose applied target the reference governor still held back at its end (by more than the
limit), is left out: its error is not the plant's. The message names the cause: without
estimation a plant that differs from the model or a constant disturbance (``estimation:`` removes
both); with it, an estimate that has not converged or a bound that holds the target back.

``estimator-diverging`` (with estimation, ``innovation`` recorded): the innovation's largest value
rose from each to the next of ``INNOVATION_WINDOWS`` equal windows of the run's last quarter (it
kept growing to the end: a transient after a setpoint change or a disturbance step rises once and
decays), and the last window's largest is above ``INNOVATION_GROWTH`` times the first quarter's
largest, above ``INNOVATION_NOISE`` times the largest standard deviation of the measurement noise
(``RunLimits.measurement_noise``: a filter's innovation stays within a few of them) and above
``INNOVATION_FLOOR`` max(1, max |y|) (round-off). Or the innovation is not finite. A warning, not a
failure: the plant's own state is judged by the failures above (a divergence that reaches it is
``diverged``, ``state-violated`` or ``infeasible``), and the growth is a trend read from the
records, which can see a steady growth of genuine surprises, e.g. a ramp of setpoints far from
the linearisation, as one.

The reference size of the divergence test is the larger of ||x(0)||_inf and the largest finite
state bound, or 1 when both are zero.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from dmpc.core.steps import NO_SEED
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.records.tracking import SegmentTrace, has_outputs, is_tracked, outputs_of, segment_traces, unreachable
from dmpc.tracking.targets import DEFAULT_MARGIN

BOUND_TOL = 1e-6
"""A bound counts as broken when it is exceeded by more than BOUND_TOL * max(1, |bound|)."""
DIVERGENCE_FACTOR = 100.0
"""The state has diverged when its norm exceeds this multiple of the reference size."""
CONVERGED_FRACTION = 1e-2
"""The final state is small when ||x(end)||_inf <= this fraction of ||x(0)||_inf (with setpoints:
||x(end) - x_s||_inf <= this fraction of the largest setpoint step)."""
CONVERGED_FLOOR = 1e-9
"""With setpoints, a final state within this times the reference size of its target has converged,
whatever the steps (a run that starts on its only target)."""
SHOWN_STEPS = 8
"""Steps listed in a message before ``...``."""
OFFSET_FRACTION = 1e-4
"""A tracked component's error at the end of its segment is an offset above this fraction of the
segment's setpoint step (``offset``)."""
SETTLED_TAIL = 0.1
"""The part of a segment (its last values) over which an error must have settled to be an offset."""
SETTLED_VALUES = 10
"""At least this many of the segment's last values (all of a shorter segment's) are looked at."""
SETTLED_CHANGE = 0.1
"""An error has settled when it stays within this fraction of its final value over the tail."""
INNOVATION_WINDOWS = 4
"""Windows of the run's last quarter over which the innovation's largest value must keep rising."""
INNOVATION_GROWTH = 10.0
"""The innovation's largest value at the end must exceed this multiple of the first quarter's."""
INNOVATION_NOISE = 10.0
"""... and this multiple of the largest standard deviation of the measurement noise."""
INNOVATION_FLOOR = 1e-9
"""... and this fraction of max(1, max |y|): growth of round-off is not a divergence."""
OFFSET_CAUSE = ("a plant that differs from the model, or a constant disturbance; `estimation:` removes such "
                'offsets (docs/algorithm.md, "Offset-free tracking")')
"""Why a run without estimation settles off its setpoint (the ``offset`` message)."""
OFFSET_CAUSE_ESTIMATED = "the estimate has not converged or a bound holds the target back"
"""Why a run with estimation still does."""

OK = "ok"
FAILED = "failed"


@dataclass(frozen=True)
class Finding:
    """One failure or warning.

    Attributes
    ----------
    kind : str
        One of the kinds in the module's table.
    message : str
        One line for a person: where and how much.
    subsystem : str or None
    steps : list of int
        The steps k where it happened (empty when not step-bound).
    amount : float or None
        How much (largest excess, norm, count), in the units of the message.
    """

    kind: str
    message: str
    subsystem: str | None = None
    steps: list[int] = field(default_factory=list)
    amount: float | None = None

    def to_json(self) -> dict:
        return {"kind": self.kind, "message": self.message, "subsystem": self.subsystem, "steps": self.steps,
                "amount": self.amount}


@dataclass(frozen=True)
class Verdict:
    """``ok`` when there is no failure (``failures`` empty); ``warnings`` never change it."""

    failures: list[Finding]
    warnings: list[Finding]

    @property
    def word(self) -> str:
        return FAILED if self.failures else OK

    @property
    def ok(self) -> bool:
        return not self.failures


@dataclass(frozen=True)
class RunLimits:
    """What the run was asked to do, for the checks that compare against it.

    Attributes
    ----------
    steps : int
        Steps planned.
    initial_rounds, rounds : int
        Jacobi caps at k = 0 and after.
    initial_tolerance, tolerance : float
        Jacobi tolerances at k = 0 and after.
    stopped : str
        Why the run stopped early, if it did ("" if not known): named in ``incomplete``.
    setpoint_margin : float
        The fraction of every bound the setpoint targets keep free (``options.setpoint_margin``):
        a request on it is reachable.
    measurement_noise : float
        The largest standard deviation of the noise the plant adds to its outputs
        (``plant.measurement_noise``; 0: exact measurements): the scale below which the
        innovation's growth is not judged (``estimator-diverging``).
    """

    steps: int
    initial_rounds: int = 200
    rounds: int = 1
    initial_tolerance: float = 1e-9
    tolerance: float = 1e-9
    stopped: str = ""
    setpoint_margin: float = DEFAULT_MARGIN
    measurement_noise: float = 0.0


def _steps_text(steps: list[int]) -> str:
    shown = ", ".join(str(k) for k in steps[:SHOWN_STEPS])
    return shown + (", ..." if len(steps) > SHOWN_STEPS else "")


def _tolerance(linear_set: LinearSet) -> float:
    bounds = np.concatenate([linear_set.lower, linear_set.upper])
    finite = np.abs(bounds[np.isfinite(bounds)])
    return BOUND_TOL * max(1.0, float(finite.max()) if finite.size else 1.0)


def state_bound_excess(system: CoupledSystem, x: np.ndarray) -> dict[str, float | None]:
    """Per subsystem of ``system``, the largest excess of x_i(k) over X_i (None: no state set; < 0: inside).

    Parameters
    ----------
    x : ndarray, shape (K+1, n)
    """
    out: dict[str, float | None] = {}
    for i, sub in enumerate(system.subsystems):
        plant_set = sub.plant_state_set
        if plant_set is None or x.shape[0] == 0:
            out[sub.name] = None
            continue
        excess = plant_set.excess(x[:, system.xs(i)])
        finite = excess[np.isfinite(excess)]
        out[sub.name] = float(finite.max()) if finite.size else None
    return out


def _bound_findings(system: CoupledSystem, values: np.ndarray, kind: str, what: str, sets: list[LinearSet | None],
                    slices: list[slice], labels: dict[str, tuple[str, ...]]) -> list[Finding]:
    found = []
    for sub, lset, sl in zip(system.subsystems, sets, slices):
        if lset is None or values.shape[0] == 0:
            continue
        excess = lset.excess(values[:, sl])
        bad = np.flatnonzero(np.isfinite(excess) & (excess > _tolerance(lset)))
        if bad.size:
            worst = float(np.max(excess[bad]))
            steps = [int(k) for k in bad]
            where = _worst_row(lset, values[int(bad[np.argmax(excess[bad])]), sl], what, labels.get(sub.name))
            found.append(Finding(kind, f"subsystem {sub.name}: {what} outside its bounds by up to {worst:.4g} "
                                       f"({where}) at {len(steps)} step(s) (k = {_steps_text(steps)})",
                                 sub.name, steps, worst))
    return found


def _worst_row(linear_set: LinearSet, value: np.ndarray, what: str, labels: tuple[str, ...] | None = None) -> str:
    """Which bound is broken most at ``value``: a component of a box (its label from the scenario,
    ``Ta [K]``, else x1, x2, ... / u1, ...), or a row of a polytope."""
    Hv = linear_set.H @ value
    with np.errstate(invalid="ignore"):
        over = np.where(np.isfinite(linear_set.upper), Hv - linear_set.upper, -np.inf)
        under = np.where(np.isfinite(linear_set.lower), linear_set.lower - Hv, -np.inf)
    row = int(np.argmax(np.maximum(over, under)))
    if linear_set.is_box:
        return labels[row] if labels else f"component {'x' if what == 'state' else 'u'}{row + 1}"
    return f"row {row} of the set"


def reference_size(system: CoupledSystem, x0: np.ndarray) -> float:
    """The larger of ||x(0)||_inf (x0) and the largest finite state bound of ``system`` (1 when both
    are 0)."""
    size = float(np.max(np.abs(x0))) if x0.size else 0.0
    for sub in system.subsystems:
        plant_set = sub.plant_state_set
        if plant_set is not None:
            bounds = np.concatenate([plant_set.lower, plant_set.upper])
            finite = np.abs(bounds[np.isfinite(bounds)])
            if finite.size:
                size = max(size, float(finite.max()))
    return size if size > 0 else 1.0


def judge(system: CoupledSystem, arrays: dict[str, np.ndarray], notes: list[str], limits: RunLimits,
          inputs_refused: dict[str, int] | None = None, reasons: list[str] | tuple[str, ...] = ("",),
          labels: dict[str, dict[str, tuple[str, ...]]] | None = None,
          traces: list[SegmentTrace] | None = None) -> Verdict:
    """The verdict of a run from its arrays (see :func:`dmpc.records.run_folder.trajectory_arrays`).

    Parameters
    ----------
    system : CoupledSystem
    arrays : dict
        ``x`` (K+1, n), ``u`` (K, m), ``rounds`` (K,), ``max_change`` (K,), and ``fallback_code``
        (K, M): per step and agent the index in ``reasons`` of why it fell back (0: it did not).
        Without ``fallback_code`` no agent fell back.
    notes : list of str
        The step records' notes (``k=0: ...``).
    limits : RunLimits
    inputs_refused : dict name -> count, optional
    reasons : sequence of str
        ``reasons[0] == ""``; ``qp <status>`` for a failed QP, ``missed``, ``lost`` or a refusal.
    labels : dict, optional
        ``{"state": {subsystem: labels}, "input": {...}, "output": {...}}``: the names and units the
        scenario gives (:func:`dmpc.core.quantities.named_labels`, the outputs' from the scenario's
        ``outputs``), used instead of ``component x1`` in the messages.
    traces : list of SegmentTrace, optional
        The run's setpoint segments (:func:`dmpc.records.tracking.segment_traces` of the same
        ``system``, ``arrays``, ``labels`` and ``limits.setpoint_margin``), when already computed.

    With estimation ``arrays`` also has ``innovation`` (K,) and ``y`` (K, p); with requests on
    outputs ``setpoint_y`` (K, p).
    """
    x, u = arrays["x"], arrays["u"]
    K = u.shape[0]
    names = [s.name for s in system.subsystems]
    failures: list[Finding] = []
    warnings: list[Finding] = []

    labels = labels or {}
    failures += _bound_findings(system, x, "state-violated", "state", [s.plant_state_set for s in system.subsystems],
                                [system.xs(i) for i in range(system.M)], labels.get("state", {}))
    failures += _bound_findings(system, u, "input-violated", "input", [s.input_set for s in system.subsystems],
                                [system.us(i) for i in range(system.M)], labels.get("input", {}))

    codes = np.asarray(arrays.get("fallback_code", np.zeros((K, system.M), int)))
    qp_failed: dict[int, list[int]] = {}  # agent -> steps where its QP failed
    missed: dict[int, list[int]] = {}
    for k, i in zip(*np.nonzero(codes)):
        target = qp_failed if reasons[codes[k, i]].startswith("qp ") else missed
        target.setdefault(int(i), []).append(int(k))
    start_failed = sorted(names[i] for i, steps in qp_failed.items() if steps and steps[0] == 0)
    if start_failed:
        seed = next((n for n in notes if n.startswith("k=0:") and NO_SEED in n), "")
        why = f"; {NO_SEED}{seed.split(NO_SEED, 1)[1]}" if seed else ""
        failures.append(Finding("infeasible-start", f"no feasible plan at k = 0 for subsystem(s) "
                                                    f"{', '.join(start_failed)}{why}", steps=[0],
                                amount=float(len(start_failed))))
    for i in sorted(qp_failed):
        later = [k for k in qp_failed[i] if k > 0]
        if later:
            causes = sorted({reasons[codes[k, i]] for k in later})
            failures.append(Finding("infeasible", f"subsystem {names[i]}: QP failed ({', '.join(causes)}) at "
                                                  f"{len(later)} step(s) (k = {_steps_text(later)}); fallback applied",
                                    names[i], later, float(len(later))))

    norms = np.max(np.abs(x), axis=1) if x.size else np.zeros(0)
    nonfinite = [int(k) for k in np.flatnonzero(~np.isfinite(norms))]
    ref = reference_size(system, x[0] if x.shape[0] else system.x0)
    if nonfinite:
        failures.append(Finding("diverged", f"the state is not finite from step {nonfinite[0]} on", steps=nonfinite,
                                amount=float("inf")))
    else:
        grown = [int(k) for k in np.flatnonzero(norms > DIVERGENCE_FACTOR * ref)]
        if grown:
            failures.append(Finding("diverged", f"||x(k)||_inf reached {float(norms.max()):.4g}, more than "
                                                f"{DIVERGENCE_FACTOR:g} x the reference size {ref:.4g} "
                                                f"(k = {_steps_text(grown)})", steps=grown, amount=float(norms.max())))

    if K < limits.steps:
        why = f" (stopped: {limits.stopped})" if limits.stopped else ""
        failures.append(Finding("incomplete", f"{K} of {limits.steps} steps recorded{why}", amount=float(K)))

    if missed:
        total = sum(len(v) for v in missed.values())
        per = ", ".join(f"{names[i]}: {len(steps)}" for i, steps in sorted(missed.items()))
        kinds = sorted({reasons[codes[k, i]] for i, steps in missed.items() for k in steps})
        warnings.append(Finding("fallbacks", f"{total} fallback(s) for plans {'/'.join(kinds)} ({per})",
                                steps=sorted({k for steps in missed.values() for k in steps}), amount=float(total)))
    refused = {name: count for name, count in (inputs_refused or {}).items() if count}
    if refused:
        warnings.append(Finding("inputs-refused", "plans refused for inputs outside U_i (" +
                                ", ".join(f"{name}: {count}" for name, count in sorted(refused.items())) + ")",
                                amount=float(sum(refused.values()))))
    if traces is None:
        traces = segment_traces(system, arrays, labels, margin=limits.setpoint_margin)
    diverged = any(f.kind == "diverged" for f in failures)
    if x.shape[0] and not diverged:
        warnings += (_output_convergence(system, x, arrays, traces, ref) if has_outputs(arrays)
                     else _convergence(x, arrays, norms, ref))
    warnings += [Finding("setpoint-unreachable",
                         f"subsystem {g['subsystem']}: {g['component']} = {g['asked']:.6g} asked from k = {g['k']} has "
                         f"no admissible steady state; the nearest, {g['target']:.6g}, is tracked instead "
                         f"(gap {g['gap']:.3g})", g["subsystem"], [g["k"]], abs(g["gap"]))
                 for g in unreachable(system, arrays, labels, limits.setpoint_margin)]
    if not diverged:
        warnings += _offsets(traces, "x_hat" in arrays)
    if "innovation" in arrays:
        warnings += _estimator(arrays, limits)
    if "x_hat" in arrays:
        warnings += _margin_exceeded(system, x, arrays["x_hat"], labels.get("state", {}))
    capped = _capped_steps(arrays, limits)
    if capped:
        change = arrays["max_change"]
        worst = max(float(change[k]) for k in capped)
        warnings.append(Finding("jacobi-cap", f"the Jacobi iteration stopped at its cap before its tolerance at "
                                              f"{len(capped)} step(s) (k = {_steps_text(capped)}; last change up to "
                                              f"{worst:.3g})", steps=capped, amount=worst))
    return Verdict(failures, warnings)


def setpoint_step(x: np.ndarray, arrays: dict[str, np.ndarray]) -> float:
    """The largest setpoint step of a run with setpoints: ||x(0) - x_s(0)||_inf, x_s the target of
    the request (``reference``) of step 0, and ||x_s(k) - x_s(k - 1)||_inf at every change of it;
    ``x`` (K+1, n), ``arrays`` the run's arrays."""
    reference = arrays["reference"]
    if not reference.shape[0]:
        return 0.0
    step = float(np.max(np.abs(x[0] - reference[0])))
    if reference.shape[0] > 1:
        step = max(step, float(np.max(np.abs(np.diff(reference, axis=0)))))
    return step


def _convergence(x: np.ndarray, arrays: dict[str, np.ndarray], norms: np.ndarray, size: float) -> list[Finding]:
    """``not-converged``: the final state ``x`` far from the origin (``norms``: ||x(k)||_inf), or with
    setpoints from the last target applied against the largest setpoint step (and that target short
    of the request's); ``size``: the reference size (:func:`reference_size`)."""
    if not is_tracked(arrays):
        start, end = float(norms[0]), float(norms[-1])
        if end > CONVERGED_FRACTION * start and end > 0:
            return [Finding("not-converged", f"||x(end)||_inf = {end:.3g}, more than {CONVERGED_FRACTION:g} x "
                                             f"||x(0)||_inf = {start:.3g}", amount=end)]
        return []
    target, reference = arrays["target"][-1], arrays["reference"][-1]
    step = setpoint_step(x, arrays)
    limit = max(CONVERGED_FRACTION * step, CONVERGED_FLOOR * size)
    end = float(np.max(np.abs(x[-1] - target)))
    found = []
    if end > limit:
        found.append(Finding("not-converged", f"||x(end) - x_s||_inf = {end:.3g} from the last target applied, more "
                                              f"than {CONVERGED_FRACTION:g} x the largest setpoint step, {step:.3g}",
                             amount=end))
    short = float(np.max(np.abs(reference - target)))
    if short > limit:
        found.append(Finding("not-converged", f"the target applied at the end is {short:.3g} short of the setpoint's "
                                              f"(the reference governor moved it {arrays['governor'][-1]:.3g} of the "
                                              "way at the last step)", amount=short))
    return found


def _output_convergence(system: CoupledSystem, x: np.ndarray, arrays: dict[str, np.ndarray],
                        traces: list[SegmentTrace], size: float) -> list[Finding]:
    """``not-converged`` of a run whose requests name outputs: the requested outputs C x(end) (and
    inputs u(end)) from the values asked at the last step, against the largest setpoint step of
    the run's segments (``traces``); and the target applied at the end short of the request's, in
    the outputs and inputs. ``x`` (K+1, n), ``arrays`` the run's, ``size`` the reference size
    (:func:`reference_size`)."""
    K = arrays["u"].shape[0]
    y_end, asked_y = outputs_of(system, x[-1]), arrays["setpoint_y"][K - 1]
    asked_u = arrays["setpoint_u"][K - 1]
    inputs = np.isfinite(asked_u)
    errors = np.concatenate([(y_end - asked_y)[np.isfinite(asked_y)], (arrays["u"][K - 1] - asked_u)[inputs]])
    step = max((abs(t.entry["step"]) for t in traces), default=0.0)
    limit = max(CONVERGED_FRACTION * step, CONVERGED_FLOOR * size)
    found = []
    end = float(np.max(np.abs(errors), initial=0.0))
    if end > limit:
        what = "outputs (C x(end)) and inputs" if inputs.any() else "outputs (C x(end))"
        found.append(Finding("not-converged", f"the requested {what} end up to {end:.3g} from the values asked, more "
                                              f"than {CONVERGED_FRACTION:g} x the largest setpoint step, {step:.3g}",
                             amount=end))
    gap = np.concatenate([outputs_of(system, arrays["reference"][-1] - arrays["target"][-1]),
                          arrays["reference_u"][-1] - arrays["target_u"][-1]])
    short = float(np.max(np.abs(gap), initial=0.0))
    if short > limit:
        found.append(Finding("not-converged", f"the target applied at the end is {short:.3g} short of the setpoint's "
                                              f"(the reference governor moved it {arrays['governor'][-1]:.3g} of the "
                                              "way at the last step)", amount=short))
    return found


def _name_and_unit(label: str) -> tuple[str, str]:
    """``Ta [K]`` as (``Ta``, `` K``): the name, and the unit with a space before it ('' without)."""
    match = re.fullmatch(r"(.*) \[(.*)\]", label)
    return (match.group(1), f" {match.group(2)}") if match else (label, "")


def short_number(value: float) -> str:
    """``value`` with two significant digits, in scientific notation without padding below 1e-3 or
    from 1e4 on (``8.5e-4``), else as ``%g`` does (``0.0046``, ``0.15``)."""
    if value == 0 or not math.isfinite(value) or 1e-3 <= abs(value) < 1e4:
        return f"{value:.2g}"
    mantissa, exponent = f"{value:.1e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def _offsets(traces: list[SegmentTrace], estimated: bool) -> list[Finding]:
    """``offset``: the segments of ``traces`` whose component settled off the value asked (the rule in
    the module's docstring); ``estimated``: the run had estimation (the message's cause)."""
    found = []
    for trace in traces:
        entry, errors = trace.entry, trace.errors
        if entry["reachable"] is False or errors.size == 0 or not np.all(np.isfinite(errors)):
            continue
        error = float(entry["error_at_end"])
        limit = max(OFFSET_FRACTION * abs(entry["step"]), trace.accuracy)
        if not abs(error) > limit or trace.held > limit:
            continue
        tail = errors[-max(math.ceil(SETTLED_TAIL * errors.size), min(errors.size, SETTLED_VALUES)):]
        if float(np.max(np.abs(tail - error))) > SETTLED_CHANGE * abs(error):
            continue
        name, unit = _name_and_unit(entry["component"])
        last = entry["until"] - 1
        cause = f" with estimation: {OFFSET_CAUSE_ESTIMATED}" if estimated else f": {OFFSET_CAUSE}"
        found.append(Finding("offset", f"{name} of subsystem {entry['subsystem']} settled {short_number(abs(error))}"
                                       f"{unit} off its setpoint {entry['asked']:.6g} at the end of its segment "
                                       f"(step {last}){cause}", entry["subsystem"], [last], abs(error)))
    return found


def _estimator(arrays: dict[str, np.ndarray], limits: RunLimits) -> list[Finding]:
    """``estimator-diverging`` from the recorded ``innovation`` (K,) and outputs ``y`` (K, p) of
    ``arrays``, with the measurement noise of ``limits`` (the rule in the module's docstring)."""
    innovation = np.asarray(arrays["innovation"], float)
    K = innovation.size
    bad = np.flatnonzero(~np.isfinite(innovation))
    if bad.size:
        k = int(bad[0])
        return [Finding("estimator-diverging", f"the estimator's innovation is not finite from step {k} on: the "
                                               "estimate diverged", steps=[k], amount=float("inf"))]
    quarter = K // 4
    if quarter < INNOVATION_WINDOWS:
        return []
    first = float(np.max(innovation[:quarter]))
    peaks = [float(np.max(w)) for w in np.array_split(innovation[K - quarter:], INNOVATION_WINDOWS)]
    y = np.asarray(arrays.get("y", np.zeros((0, 0))), float)
    scale = max(1.0, float(np.max(np.abs(y), initial=0.0)) if np.all(np.isfinite(y)) else 1.0)
    floor = max(INNOVATION_GROWTH * first, INNOVATION_NOISE * limits.measurement_noise, INNOVATION_FLOOR * scale)
    if not (all(b > a for a, b in zip(peaks, peaks[1:])) and peaks[-1] > floor):
        return []
    k = K - quarter + int(np.argmax(innovation[K - quarter:]))
    return [Finding("estimator-diverging", f"the estimator's innovation ||y - C x^ - C_d d^||_inf kept growing over "
                                           f"the last quarter of the run, to {peaks[-1]:.3g} at step {k} "
                                           f"({peaks[-1] / first if first > 0 else float('inf'):.3g} x the first "
                                           f"quarter's largest, {first:.3g}): the estimate is drifting away from the "
                                           "plant, which differs from the model more than the estimator can follow "
                                           '(docs/algorithm.md, "Offset-free tracking")', steps=[k],
                    amount=peaks[-1])]


def _margin_exceeded(system: CoupledSystem, x: np.ndarray, x_hat: np.ndarray,
                     labels: dict[str, tuple[str, ...]]) -> list[Finding]:
    """``estimation-margin``: per subsystem with an estimation margin, the steps where the estimation
    error |x(k) - x^(k)| of a state given a margin > 0 (``x`` (K+1, n), ``x_hat`` (K, n)) exceeded it by
    more than ``BOUND_TOL`` (relative to max(1, margin)), with the largest excess and the state it was in."""
    found = []
    K = x_hat.shape[0]
    for i, sub in enumerate(system.subsystems):
        if sub.state_margin is None or K == 0:
            continue
        error = np.abs(x[:K, system.xs(i)] - x_hat[:, system.xs(i)])
        # a state given no margin (0) is not judged: nothing was promised for it
        excess = np.where(sub.state_margin > 0, error - sub.state_margin, -np.inf)
        bad = np.flatnonzero((excess > BOUND_TOL * np.maximum(1.0, sub.state_margin)).any(axis=1))
        if not bad.size:
            continue
        k, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
        named = labels.get(sub.name)
        state = named[j] if named else f"x{j + 1}"
        found.append(Finding("estimation-margin", f"the estimation error of {state} of subsystem {sub.name} reached "
                                                  f"{error[k, j]:.3g}, over its margin {sub.state_margin[j]:g}, at "
                                                  f"{bad.size} step(s) (first k = {int(bad[0])}): the state bounds "
                                                  "are not guaranteed there (docs/algorithm.md, \"Offset-free "
                                                  "tracking\")", sub.name, [int(b) for b in bad],
                             float(excess[k, j])))
    return found


def _capped_steps(arrays: dict[str, np.ndarray], limits: RunLimits) -> list[int]:
    rounds, change = arrays["rounds"], arrays["max_change"]
    capped = []
    for k in range(rounds.shape[0]):
        cap, tol = ((limits.initial_rounds, limits.initial_tolerance) if k == 0
                    else (limits.rounds, limits.tolerance))
        if cap > 1 and rounds[k] >= cap and not (change[k] < tol):
            capped.append(k)
    return capped
