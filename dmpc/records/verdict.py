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
========================  ========  ==============================================================

With setpoints, ``not-converged`` measures the final state from the target applied at the last
step against the largest setpoint step (||x(0) - x_s(0)||_inf and every change of the request's
target, :func:`setpoint_step`), not against a start that may sit on its target, and also says when
the target applied had not reached the request's yet. A request's gap counts once it exceeds the
target solver's accuracy (:func:`dmpc.records.tracking.gap_tolerance`): a request exactly on the
setpoint margin is met.

The reference size of the divergence test is the larger of ||x(0)||_inf and the largest finite
state bound, or 1 when both are zero.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dmpc.core.steps import NO_SEED
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.records.tracking import is_tracked, unreachable
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
    """

    steps: int
    initial_rounds: int = 200
    rounds: int = 1
    initial_tolerance: float = 1e-9
    tolerance: float = 1e-9
    stopped: str = ""
    setpoint_margin: float = DEFAULT_MARGIN


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
        if sub.state_set is None or x.shape[0] == 0:
            out[sub.name] = None
            continue
        excess = sub.state_set.excess(x[:, system.xs(i)])
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
        if sub.state_set is not None:
            bounds = np.concatenate([sub.state_set.lower, sub.state_set.upper])
            finite = np.abs(bounds[np.isfinite(bounds)])
            if finite.size:
                size = max(size, float(finite.max()))
    return size if size > 0 else 1.0


def judge(system: CoupledSystem, arrays: dict[str, np.ndarray], notes: list[str], limits: RunLimits,
          inputs_refused: dict[str, int] | None = None, reasons: list[str] | tuple[str, ...] = ("",),
          labels: dict[str, dict[str, tuple[str, ...]]] | None = None) -> Verdict:
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
        ``{"state": {subsystem: labels}, "input": {...}}``: the names and units the scenario gives
        (:func:`dmpc.core.quantities.named_labels`), used instead of ``component x1`` in the messages.
    """
    x, u = arrays["x"], arrays["u"]
    K = u.shape[0]
    names = [s.name for s in system.subsystems]
    failures: list[Finding] = []
    warnings: list[Finding] = []

    labels = labels or {}
    failures += _bound_findings(system, x, "state-violated", "state", [s.state_set for s in system.subsystems],
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
    if x.shape[0] and not any(f.kind == "diverged" for f in failures):
        warnings += _convergence(x, arrays, norms, ref)
    warnings += [Finding("setpoint-unreachable",
                         f"subsystem {g['subsystem']}: {g['component']} = {g['asked']:.6g} asked from k = {g['k']} has "
                         f"no admissible steady state; the nearest, {g['target']:.6g}, is tracked instead "
                         f"(gap {g['gap']:.3g})", g["subsystem"], [g["k"]], abs(g["gap"]))
                 for g in unreachable(system, arrays, labels, limits.setpoint_margin)]
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


def _capped_steps(arrays: dict[str, np.ndarray], limits: RunLimits) -> list[int]:
    rounds, change = arrays["rounds"], arrays["max_change"]
    capped = []
    for k in range(rounds.shape[0]):
        cap, tol = ((limits.initial_rounds, limits.initial_tolerance) if k == 0
                    else (limits.rounds, limits.tolerance))
        if cap > 1 and rounds[k] >= cap and not (change[k] < tol):
            capped.append(k)
    return capped
