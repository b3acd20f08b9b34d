"""The coordinator's setpoints: requests that arrive while the run goes on, their checks and
answers, and the tracker that decides each step's target (docs/algorithm.md, "Setpoints";
docs/protocol.md, "Setpoints while a run goes on").
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from dmpc.bus.messages import Setpoint, SetpointAnswer
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.methods import lacks
from dmpc.security.rejects import MAX_MAGNITUDE
from dmpc.tracking.schedule import SetpointEntry
from dmpc.tracking.targets import Request, Target
from dmpc.tracking.tracker import Tracker, TrackingStep


class SetpointIntake:
    """The setpoints of one run.

    Parameters
    ----------
    system : CoupledSystem
    run_id : str
    steps : int
        The run's length: a request must hold from a step before it.
    tracker : Tracker or None
        The targets (with the scenario's schedule); None for a method that does not track
        setpoints: every step is controlled around the origin, and requests are refused.
    method : str
        The run's method (a refusal for lack of a tracker names it).

    Attributes
    ----------
    origin : Target
        The target of every step while nothing is tracked (and of step 0).
    """

    def __init__(self, system: CoupledSystem, run_id: str, steps: int, tracker: Tracker | None,
                 method: str) -> None:
        self.system = system
        self.method = method
        self.run_id = run_id
        self.steps = steps
        self.tracker = tracker
        self.names = [s.name for s in system.subsystems]
        self.index = {name: i for i, name in enumerate(self.names)}
        self.origin = Target.origin(system.n, system.m)

    def answer(self, msg: Setpoint, first_undecided: int, finished: bool) -> tuple[SetpointAnswer, str]:
        """Take the request ``msg`` from step ``first_undecided`` (the first step whose target is not
        decided yet), or refuse it and say why.

        Accepted, it joins the tracker's schedule from that step (NaN where free; an empty x or u
        leaves every component free). Refused (also a run that is ``finished``), nothing changes.

        Returns
        -------
        (SetpointAnswer, note)
            The answer: accepted with ``k`` the first step the request holds at, or refused
            (``k`` = -1) with the reason. ``note``: what the record of the step it arrived in says
            of it ("" when refused).
        """
        refusal = self.refusal(msg, first_undecided, finished)
        if refusal is not None:
            return refusal, ""
        assert self.tracker is not None  # checked by problem()
        entry = self._entry(msg, first_undecided)
        self.tracker.add(entry)
        x, u = self._asked(msg)
        note = (f"setpoint from {msg.sender} (id {msg.id}): subsystem {msg.subsystem} "
                f"{_components_text('x', x)}, {_components_text('u', u)} from step {entry.at}")
        return SetpointAnswer(self.run_id, msg.id, msg.subsystem, True, entry.at), note

    def _asked(self, msg: Setpoint) -> tuple[np.ndarray, np.ndarray]:
        """The states (n_i,) and inputs (m_i,) the request ``msg`` asks for, NaN where free, in the
        plant's units as sent (its subsystem and sizes checked by :meth:`problem`)."""
        sub = self.system.subsystems[self.index[msg.subsystem]]
        return _request_part(msg.x, sub.n), _request_part(msg.u, sub.m)

    def _entry(self, msg: Setpoint, at: int) -> SetpointEntry:
        """The schedule's entry of the request ``msg`` (checked by :meth:`problem`) from step ``at``, in
        the model's deviations (the request is in the plant's units)."""
        i = self.index[msg.subsystem]
        sub = self.system.subsystems[i]
        x, u = self._asked(msg)
        if sub.x_op is not None:
            x, u = x - sub.state_offset, u - sub.input_offset
        if self.tracker is not None and self.tracker.outputs is not None:
            # with estimation a request names outputs: each requested state is an output of its own
            # (checked by problem())
            y = np.full(sub.p, np.nan)
            for c in np.flatnonzero(~np.isnan(x)):
                y[_output_of(sub.output_matrix, int(c))] = x[c]
            return SetpointEntry(at=at, index=i, x=np.full(sub.n, np.nan), u=u, source=msg.sender, y=y)
        return SetpointEntry(at=at, index=i, x=x, u=u, source=msg.sender)

    def needs(self, msgs: Sequence[Setpoint], first_undecided: int,
              finished: bool) -> tuple[list[SetpointAnswer | None], list[Request]]:
        """What taking the requests ``msgs``, in their order, from step ``first_undecided`` would need:
        the refusal of each that is refused, and the requests whose targets must be computed first
        (none: they can be taken at once).

        Parameters
        ----------
        msgs : sequence of Setpoint
            The requests, as :meth:`answer` takes them.
        first_undecided : int
            The first step whose target is not decided yet, where they would hold from.
        finished : bool
            The run is over.

        Returns
        -------
        (list of SetpointAnswer or None, list of Request)
            Per request its refusal, or None if it would be taken; and the requests of the
            schedule with those taken added, from ``first_undecided`` on, whose targets are not
            known yet (:meth:`Tracker.unknown <dmpc.tracking.tracker.Tracker.unknown>`).
        """
        refusals = [self.refusal(msg, first_undecided, finished) for msg in msgs]
        entries = [self._entry(msg, first_undecided) for msg, refusal in zip(msgs, refusals) if refusal is None]
        if not entries:
            return refusals, []
        assert self.tracker is not None  # checked by problem()
        return refusals, self.tracker.unknown(entries)

    def refusal(self, msg: Setpoint, first_undecided: int, finished: bool) -> SetpointAnswer | None:
        """The answer that refuses the request ``msg`` from step ``first_undecided`` (the run
        ``finished`` or not), or None if it would be taken (:meth:`problem` says why not)."""
        try:
            problem = self.problem(msg, first_undecided, finished)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the run
            problem = f"malformed: {type(exc).__name__}"
        return None if problem is None else SetpointAnswer(self.run_id, msg.id, msg.subsystem, False, -1, problem)

    def learn(self, known: Iterable[tuple[Request, Target]]) -> None:
        """Keep the targets ``known`` (request, its target), computed beside the run, for the steps
        that will need them (nothing without a tracker)."""
        if self.tracker is not None:
            self.tracker.learn(known)

    def problem(self, msg: Setpoint, first_undecided: int, finished: bool) -> str | None:
        """Why the request cannot be taken from step ``first_undecided``, or None.

        Parameters
        ----------
        msg : Setpoint
            The request: its run and subsystem, and the x (n_i,) and u (m_i,) it asks for (or
            (0,): all free), each finite or NaN and inside a box X_i or U_i.
        first_undecided : int
            The first step whose target is not decided yet, where the request would hold from.
        finished : bool
            The run is over (no request is taken then).
        """
        if msg.run != self.run_id:
            return f"wrong run id '{msg.run}' (this run is '{self.run_id}')"
        if self.tracker is None:
            lacking = lacks(self.method, "tracks_setpoints")
            return str(lacking) if lacking is not None else f"this run of method '{self.method}' has no tracker"
        if finished:
            return "the run is finished"
        if first_undecided >= self.steps:
            return f"too late: the run's last step ({self.steps - 1}) is already decided"
        i = self.index.get(msg.subsystem)
        if i is None:
            shown = ", ".join(self.names[:8]) + (", ..." if len(self.names) > 8 else "")
            return f"unknown subsystem '{msg.subsystem}' (known: {shown})"
        sub = self.system.subsystems[i]
        problem = (_component_problem(np.asarray(msg.x, dtype=float), "x", sub.n, sub.state_set, msg.subsystem,
                                      None if sub.x_op is None else sub.state_offset)
                   or _component_problem(np.asarray(msg.u, dtype=float), "u", sub.m, sub.input_set, msg.subsystem,
                                         None if sub.x_op is None else sub.input_offset))
        if problem is None and self.tracker.outputs is not None:
            x = _request_part(np.asarray(msg.x, dtype=float), sub.n)
            if not np.isnan(np.asarray(msg.u, dtype=float)).all():
                return "u: this run estimates its state (estimation): a request names measured states only"
            for c in np.flatnonzero(~np.isnan(x)):
                if _output_of(sub.output_matrix, int(c)) < 0:
                    return (f"x[{c}]: this run estimates its state (estimation), and state {c} of subsystem "
                            f"'{msg.subsystem}' is not measured on its own: a request names measured states only")
        return problem

    def close_step(self, k: int, eta: np.ndarray,
                   disturbance: np.ndarray | None = None) -> tuple[TrackingStep | None, Target]:
        """What step k tracked and the target of step k + 1, from the terminal states eta (n,) of
        step k's plans (and with estimation the ``disturbance`` estimate (n_d,)): (None, the origin)
        without a tracker; (the tracker's idle step, the origin) while nothing was ever requested."""
        if self.tracker is None:
            return None, self.origin
        if not self.tracker.active:
            return self.tracker.idle, self.origin
        return self.tracker.step(k), self.tracker.advance(k + 1, eta, disturbance)


def _output_of(C: np.ndarray, c: int) -> int:
    """The row of ``C`` (p_i, n_i) that measures state ``c`` alone (a unit row), or -1."""
    unit = np.zeros(C.shape[1])
    unit[c] = 1.0
    rows = np.flatnonzero((C == unit).all(axis=1))
    return int(rows[0]) if rows.size else -1


def _request_part(values: np.ndarray, size: int) -> np.ndarray:
    """A subsystem's requested components (size,), NaN where free: ``values`` or, empty, all free."""
    values = np.asarray(values, dtype=float)
    return np.full(size, np.nan) if values.size == 0 else values.copy()


def _component_problem(values: np.ndarray, kind: str, size: int, bounds: LinearSet | None, name: str,
                       offset: np.ndarray | None = None) -> str | None:
    """Why the requested states (``kind`` x) or inputs (u) of subsystem ``name`` cannot be taken, or
    None: ``size`` entries or none, NaN or finite, inside a box X_i or U_i (a polytope's are left to
    the target, which keeps inside it). With an operating point, ``offset`` (size,) is its value:
    the request is in the plant's units, ``bounds`` in the model's deviations."""
    if values.ndim != 1 or values.size not in (0, size):
        what = f"n_i = {size} states" if kind == "x" else f"m_i = {size} inputs"
        return f"{kind}: expected {size} entries ({what} of subsystem '{name}') or none, got {values.size}"
    for c, value in enumerate(values):
        if math.isnan(value):
            continue
        if not abs(value) <= MAX_MAGNITUDE:
            return f"{kind}[{c}]: expected a finite number up to {MAX_MAGNITUDE:g} in size, or NaN for a free one"
        at = 0.0 if offset is None else float(offset[c])
        if bounds is not None and bounds.is_box and not bounds.lower[c] + at <= value <= bounds.upper[c] + at:
            return (f"{kind}[{c}]: the target {value:g} of subsystem '{name}' is outside "
                    f"{'X_i' if kind == 'x' else 'U_i'} [{bounds.lower[c] + at:g}, {bounds.upper[c] + at:g}]")
    return None


def _components_text(kind: str, values: np.ndarray) -> str:
    """``x = [1, free]``, or ``x free`` when nothing is requested."""
    if np.isnan(values).all():
        return f"{kind} free"
    return f"{kind} = [{', '.join('free' if math.isnan(v) else f'{v:g}' for v in values)}]"
