"""The coordinator's side of setpoint tracking: which target each step applies.

Per step k the schedule gives the request (the latest entry of each subsystem at or before k),
the request its target (the reference, :class:`~dmpc.tracking.targets.TargetSpace`), and the
reference governor the target applied at k, moved toward the reference no faster than the plans
of step k - 1 allow (:class:`~dmpc.tracking.governor.ReferenceGovernor`). Step 0 applies the
origin, the target the design and its start check were made for; the governor moves from there
at the end of step 0.

Pure: no bus, no clock. Targets of requests seen before are kept (a request costs one QP the
first time it is seen, nothing after). The targets of the scenario's schedule are computed when the
tracker is built, before the run; a request that arrives while the run goes on can have its targets
computed elsewhere first (:meth:`Tracker.unknown` names them, :meth:`Tracker.learn` keeps them), so
that no step waits for a QP.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dmpc.core.system import CoupledSystem
from dmpc.estimation.targets import OffsetFreeTargets
from dmpc.offline.terminal_set import TerminalSet
from dmpc.tracking.governor import ReferenceGovernor
from dmpc.tracking.schedule import Schedule, SetpointEntry
from dmpc.tracking.targets import DEFAULT_MARGIN, Request, Target, TargetSpace

if TYPE_CHECKING:
    import scipy.sparse as sp


@dataclass(frozen=True, eq=False)
class TrackingStep:
    """What one step tracked: asked for, its target, the target applied and how far it moved.

    Attributes
    ----------
    request : Request
        The requested components, (n,) and (m,), NaN where free.
    reference : Target
        The target of the request (the nearest admissible one when it is unreachable).
    applied : Target
        The target the step's controllers worked around.
    theta : float
        The fraction of the way from the previous step's applied target to the reference this
        step's took (1: the reference is applied).
    active : bool
        False while nothing was ever requested (the origin, as without setpoints).
    """

    request: Request
    reference: Target
    applied: Target
    theta: float
    active: bool = True


class Tracker:
    """Targets of one run.

    Parameters
    ----------
    system : CoupledSystem
    terminal : TerminalSet
        X^f of the design.
    closed_loop : ndarray or sparse matrix, shape (n, n)
        A + BK.
    gain : ndarray or sparse matrix, shape (m, n)
        K, block diagonal.
    entries : iterable of SetpointEntry
        The scenario's schedule.
    margin : float
        Targets keep this fraction of every bound free (:class:`TargetSpace`).
    outputs : OffsetFreeTargets, optional
        With estimation: the targets of requests on outputs, steady states of the model with the
        disturbance estimate (docs/algorithm.md, "Offset-free tracking"), recomputed at every step
        from the estimate of :meth:`advance` (a back-substitution, no QP while the target keeps
        its bounds).
    """

    def __init__(self, system: CoupledSystem, terminal: TerminalSet, closed_loop: np.ndarray | sp.spmatrix,
                 gain: np.ndarray | sp.spmatrix, entries: tuple[SetpointEntry, ...] = (),
                 margin: float = DEFAULT_MARGIN, outputs: OffsetFreeTargets | None = None) -> None:
        self.system = system
        self.outputs = outputs
        self.disturbance: np.ndarray | None = None  # the latest disturbance estimate (with outputs)
        self.space = TargetSpace(system, margin)
        self.governor = ReferenceGovernor(self.space, terminal, closed_loop, gain)
        self.schedule = Schedule(system, entries)
        self.applied = Target.origin(system.n, system.m)
        self.theta = 1.0
        origin = Target.origin(system.n, system.m)
        self.idle = TrackingStep(Request.free(system.n, system.m), origin, origin, 1.0, active=False)
        """What a step tracks while nothing was ever requested (one object for every such step)."""
        self._targets: dict[bytes, tuple[Request, Target]] = {}
        self.unreachable: dict[bytes, tuple[int, Request, Target]] = {}  # first step each was asked at
        if outputs is None:
            self.learn((request, self.space.target(request)) for request in self.unknown())
        else:  # every pattern of the schedule factored now, before the run
            for request in self.unknown():
                if request.y is not None:
                    outputs.pattern(~np.isnan(request.y))

    @property
    def active(self) -> bool:
        """True once anything was requested: the records carry the targets from then on."""
        return bool(self.schedule)

    def add(self, entry: SetpointEntry) -> None:
        """A request ``entry`` that arrived while the run goes on (its ``at`` is a step not yet decided)."""
        self.schedule = self.schedule.with_entry(entry)

    def unknown(self, entries: Sequence[SetpointEntry] = ()) -> list[Request]:
        """The requests whose targets are not known yet that the schedule, with ``entries`` added in
        their order, makes from the first of their steps on (without entries: from step 0 on): at
        that step and at every later step where an entry takes effect; each once, none that asks
        for nothing (the origin)."""
        schedule = self.schedule
        for entry in entries:
            schedule = schedule.with_entry(entry)
        start = min((entry.at for entry in entries), default=0)
        found: dict[bytes, Request] = {}
        for k in [start] + [c for c in schedule.change_steps() if c > start]:
            request = schedule.request(k)
            key = _key(request)
            if key not in self._targets and key not in found and not request.is_free:
                found[key] = request
        return list(found.values())

    def learn(self, known: Iterable[tuple[Request, Target]]) -> None:
        """Keep the targets ``known`` (request, its target), computed beforehand by
        :meth:`TargetSpace.target <dmpc.tracking.targets.TargetSpace.target>`: the steps that need
        them take them from here."""
        for request, target in known:
            self._targets.setdefault(_key(request), (request, target))

    def reference(self, k: int) -> tuple[Request, Target]:
        """The request that holds at step k and its target (computed now if it is not known yet;
        a request on outputs: from the latest disturbance estimate)."""
        request = self.schedule.request(k)
        if request.y is not None and self.outputs is not None and not request.is_free:
            return request, self._output_target(request)
        key = _key(request)
        known = self._targets.get(key)
        if known is None:
            known = self._targets[key] = (request, self.space.target(request))
        if not known[1].reachable:
            self.unreachable.setdefault(key, (k, request, known[1]))
        return known

    def step(self, k: int) -> TrackingStep:
        """What step k tracks (its applied target is the current one)."""
        if k == 0:
            self.theta = 1.0 if self.reference(0)[1].is_origin else 0.0
        request, reference = self.reference(k)
        return TrackingStep(request, reference, self.applied, self.theta)

    def advance(self, k: int, eta: np.ndarray, disturbance: np.ndarray | None = None) -> Target:
        """Decide the target of step ``k`` from the terminal states eta (n,) of step k - 1's plans
        (and, with estimation, the disturbance estimate (n_d,) the next step starts from)."""
        if disturbance is not None:
            self.disturbance = disturbance
        _, reference = self.reference(k)
        decided = self.governor.step(eta, self.applied, reference)
        self.applied, self.theta = decided.target, decided.theta
        return self.applied


    def _output_target(self, request: Request) -> Target:
        """The target of a request on outputs for the latest disturbance estimate: the affine map's
        while it keeps the bounds (with the margin), else the steady-state QP's; where none keeps
        them, the target applied now (the request is then unreachable as asked)."""
        assert self.outputs is not None and request.y is not None
        d_hat = self.disturbance if self.disturbance is not None else np.zeros(self.outputs.model.nd)
        found = self.outputs.target(request.y, d_hat)
        reachable = found.inside
        if not reachable:
            bounded = self.outputs.bounded(request.y, d_hat)
            if bounded is None:
                return self.applied
            found = bounded
        n, m = self.system.n, self.system.m
        return Target(found.x, found.u, self.space.scale(found.x, found.u), np.full(n, np.nan), np.full(m, np.nan),
                      reachable)


def _key(request: Request) -> bytes:
    """The bytes that tell requests apart (NaN, free, included)."""
    return request.x.tobytes() + request.u.tobytes() + (b"" if request.y is None else b"y" + request.y.tobytes())
