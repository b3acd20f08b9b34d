"""The coordinator's node: readiness, releases, deadlines, records, stop.

Hosts the pure Coordinator on a bus (with the simulated plant in it, or a link to a plant outside). In ``realtime`` mode step k is released at
``t0 + k dt`` on the bus clock and each round has a deadline; in ``lockstep`` the next step
follows as soon as the last plan is in.

Whatever arrives is decoded here; a plan whose sender matches its key goes to the coordinator,
which accepts it or says why not. Invalid messages are dropped and counted per sender
(``rejected``, in the run's summary), never raised.
"""
from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Protocol

from dmpc.bus import keys
from dmpc.bus.codec import MAX_REASON, DecodeError, VersionMismatch, decode, encode
from dmpc.bus.interface import Bus, Reply
from dmpc.bus.messages import (
    PROTOCOL_VERSION,
    Kept,
    PlanMessage,
    Ready,
    Setpoint,
    SetpointAnswer,
    Stop,
    design_claim,
)
from dmpc.coordinator.barrier import (
    ApplyInputs,
    Coordinator,
    PlanRefused,
    RoundOpened,
    RunFinished,
    SendRelease,
    StepCompleted,
)
from dmpc.coordinator.target_worker import Known, TargetWorker
from dmpc.core.steps import StepRecord
from dmpc.plant.link import PlantLink
from dmpc.plant.state_inbox import Measurement
from dmpc.security.rejects import STALE, Rejections

log = logging.getLogger("dmpc.plant")
NAMED_DESIGNS = 3  # differing designs spelled out in a start-up failure (the Stop reason is bounded)
MAX_WAITING = 256
"""Setpoint requests that may wait for their targets at once; one beyond is refused at once."""


def _shown(text: str) -> str:
    """``text`` (which may come from the sender) with non-printable characters as ``?``."""
    return "".join(c if c.isprintable() else "?" for c in text)


def design_text(digest: str, scenario: str = "", horizon: int = 0) -> str:
    """``<digest> (scenario '<name>', horizon <N>)``, leaving out what is unknown."""
    known = ([f"scenario '{_shown(scenario)}'"] if scenario else []) + ([f"horizon {horizon}"] if horizon else [])
    return _shown(digest) + (f" ({', '.join(known)})" if known else "")


class MessageCount:
    """The agents' answers that reached the coordinator: per agent, plan messages and kept notices
    and their bytes (each published once, whoever else received it)."""

    def __init__(self) -> None:
        self.counts: dict[str, dict[str, int]] = {}

    def add(self, sender: str, kind: str, size: int) -> None:
        """Count one answer.

        Parameters
        ----------
        sender : str
            The agent's name (the message's ``sender``).
        kind : {"plan", "kept"}
            A plan message or a kept notice.
        size : int
            Its payload's length in bytes.
        """
        entry = self.counts.setdefault(sender, {"plan": 0, "kept": 0, "bytes": 0})
        entry[kind] += 1
        entry["bytes"] += size

    def summary(self, names: list[str]) -> dict:
        """``summary.json``'s ``messages``: totals and, per agent, ``plan_messages``,
        ``kept_notices`` and ``bytes``.

        Parameters
        ----------
        names : list of str
            The agents' names, in the scenario's order: ``per_agent`` has one entry for each
            (zeros for one that sent nothing), and only these count in the totals.
        """
        per = {name: {"plan_messages": self.counts.get(name, {}).get("plan", 0),
                      "kept_notices": self.counts.get(name, {}).get("kept", 0),
                      "bytes": self.counts.get(name, {}).get("bytes", 0)} for name in names}
        return {"plan_messages": sum(p["plan_messages"] for p in per.values()),
                "kept_notices": sum(p["kept_notices"] for p in per.values()),
                "bytes": sum(p["bytes"] for p in per.values()), "per_agent": per}


@dataclass(frozen=True)
class _Request:
    """A setpoint request as it arrived: the message, and how its answer goes back (published on
    ``setpoint-answer/<sender>``, or the reply of its query)."""

    msg: Setpoint
    respond: Reply


class RunObserver(Protocol):
    """Who watches the run from outside it (the live view's telemetry): told of each completed
    step and of the end; it must never block the coordinator."""

    def step(self, record: StepRecord, node: "CoordinatorNode") -> None:
        """A step completed with ``record``; ``node`` tells who is alive, ready, and what was dropped.

        Parameters
        ----------
        record : StepRecord
            The completed step's record, as the run folder got it.
        node : CoordinatorNode
            The coordinator node that completed it.
        """
        ...

    def summary(self, summary: dict) -> None:
        """The run ended with ``summary`` (``summary.json``'s content)."""
        ...

    def close(self) -> None:
        ...


class CoordinatorNode:
    """The coordinator on a bus, with the simulated plant or the link to a plant outside.

    Parameters
    ----------
    bus : Bus
    coordinator : Coordinator
        Built with this bus's clock (``clock=bus.now``), so that the records have the plans'
        latency and the steps' times.
    design_digest : str
        Every agent's Ready must carry the same digest.
    on_step : callable StepRecord -> None
        Called for every completed step (the run folder appends it).
    mode : {"lockstep", "realtime"}
    dt : float
        Step period in realtime mode (seconds).
    deadline : float or None
        Seconds after a round's release after which missing plans are missed.
    scenario : str
        The scenario's name, to say how an agent's differing design differs.
    telemetry : RunObserver, optional
        Gets every completed step after ``on_step``, for observers (it never blocks).
    plant_timeout : float or None
        With a plant outside (the coordinator built with ``plant=None``): seconds to wait for the
        state of each step (docs/protocol.md); x(0) is awaited with the agents' readiness.
    targets : TargetWorker, optional
        Computes the targets of setpoint requests beside the run: a request is taken at the first
        step boundary after its targets are known, and answered then. Without one (the in-memory
        bus), a request is taken as it arrives and its targets computed when a step needs them.
    """

    def __init__(self, bus: Bus, coordinator: Coordinator, design_digest: str,
                 on_step: Callable[[StepRecord], None], mode: str = "lockstep", dt: float = 0.1,
                 deadline: float | None = None, scenario: str = "", telemetry: RunObserver | None = None,
                 plant_timeout: float | None = None, targets: TargetWorker | None = None) -> None:
        self.bus = bus
        self.coordinator = coordinator
        self.run_id = coordinator.run_id
        self.names = coordinator.names
        self.design_digest = design_digest
        self.scenario = scenario
        self.mismatched: dict[str, Ready] = {}  # the latest Ready with another design, per agent
        self.on_step = on_step
        self.mode = mode
        self.dt = dt
        self.deadline = deadline
        self.telemetry = telemetry
        self.ready: set[str] = set()
        self.alive: set[str] = set()
        self.started = False
        self.finished = False
        self.failure = ""
        sources = [] if coordinator.plant is not None else keys.state_sources(self.names)
        # how this process names itself: the plant process hosts the coordinator unless the plant is outside
        self.who = "plant" if coordinator.plant is not None else "coordinator"
        self.rejects = Rejections(log, self.who, bus.now, self.names + sources)
        self.rejected: dict[str, int] = self.rejects.counts
        self.other_versions: dict[str, int | None] = {}  # per agent or source: the protocol version it spoke
        self.x0: Measurement | None = None  # x(0) (or the outputs) from a plant outside, once complete
        self.link: PlantLink | None = None
        if coordinator.plant is None:
            self.link = PlantLink(bus, coordinator.system, self.run_id, self.rejects, self._on_measured, self.fail,
                                  timeout=plant_timeout if plant_timeout is not None else 10.0,
                                  outputs=coordinator.estimates)
            self.link.await_first()
        self._t0 = 0.0
        self._opened_step = -1  # the last step whose time was started
        self._stop_payload: bytes | None = None
        self.messages = MessageCount()
        self.targets = targets
        self._waiting: deque[_Request] = deque()  # setpoint requests not yet taken, in the order they arrived
        self._batch: list[_Request] = []  # those whose targets the worker computes now (they left _waiting)
        bus.subscribe(keys.plan(self.run_id, "*"), self._on_plan, hot=True)
        bus.subscribe(keys.kept(self.run_id, "*"), self._on_kept)  # not hot: run() waits on the plans, a queued notice wakes it
        bus.subscribe(keys.ready(self.run_id, "*"), self._on_ready)
        bus.subscribe(keys.setpoint_prefix(self.run_id), self._on_setpoint)
        bus.serve(keys.setpoint_prefix(self.run_id), self._on_setpoint_query)
        bus.watch_alive(keys.alive_prefix(self.run_id), self._on_alive)

    def counts(self) -> dict:
        """What this node counted, for ``summary.json``: messages dropped (``rejected`` and their
        ``rejected_reasons``), copies ignored (``duplicates``), plans refused (``inputs_refused``),
        and the agents' plan messages and kept notices that reached it (``messages``); with a plant
        outside that reported outputs in place of states, the subsystems it did so for
        (``outputs_reported``: their recorded states are estimates)."""
        c = self.coordinator
        return {"rejected": self.rejected, "rejected_reasons": self.rejects.reasons, "duplicates": c.duplicates,
                "inputs_refused": c.inputs_refused, "messages": self.messages.summary(self.names),
                **({"outputs_reported": sorted(c.outputs_reported)} if c.outputs_reported else {})}

    def announce(self) -> None:
        self.bus.declare_alive(keys.alive(self.run_id, keys.COORDINATOR_ROLE))

    # ------------------------------------------------------------------ receive
    def _reject(self, sender: str, why: str) -> None:
        self.rejects(sender, why)

    def _decoded(self, name: str, payload: bytes) -> object | None:
        """The message in ``payload``, or None (counted against ``name``) if it does not decode."""
        try:
            return decode(payload)
        except DecodeError as exc:
            if isinstance(exc, VersionMismatch) and name in self.names:
                self.other_versions[name] = exc.version
            self._reject(name, str(exc))
            return None

    def _on_ready(self, key: str, payload: bytes) -> None:
        name = keys.last_chunk(key)
        msg = self._decoded(name, payload)
        if msg is None:
            return
        if not isinstance(msg, Ready) or msg.run != self.run_id or msg.sender != name or name not in self.names:
            self._reject(name, "invalid ready message")
            return
        if msg.design_digest != self.design_digest:
            # dropped rather than fatal: anyone on the bus could send it; the run waits for a
            # matching Ready and, if none comes, its start-up failure names the difference
            self.mismatched[name] = msg
            self._reject(name, f"design: {self._mismatch_text(name)}; this {self.who} uses design "
                               f"{self._own_design()}; give every process the same scenario")
            return
        self.mismatched.pop(name, None)
        self.ready.add(name)
        if self.started:
            if self.coordinator.on_agent_back(name):
                log.warning("coordinator: agent %s back at step %d; waited for again from the next round", name,
                            self.coordinator.k)
        else:
            self._maybe_start()

    def _mismatch_text(self, name: str) -> str:
        msg = self.mismatched[name]
        return f"{design_claim(name, _shown(msg.design_digest))}{design_text('', msg.scenario, msg.horizon)}"

    def _own_design(self) -> str:
        return design_text(self.design_digest, self.scenario, self.coordinator.N)

    def design_mismatch(self, names: list[str]) -> str:
        """How the designs of those of ``names`` that sent another design differ ("" if none did).

        Their last ``Ready`` is what is named: a forged one can mislead this text, but it never
        stops the run before the start-up timeout.
        """
        differing = [name for name in names if name in self.mismatched]
        if not differing:
            return ""
        shown = [self._mismatch_text(name) for name in differing[:NAMED_DESIGNS]]
        if len(differing) > NAMED_DESIGNS:
            shown.append(f"and {len(differing) - NAMED_DESIGNS} more")
        head = "a design differs" if len(differing) == 1 else f"{len(differing)} designs differ"
        return (f"{head} from this {self.who}'s: {'; '.join(shown)}; this {self.who} uses design {self._own_design()}; "
                "give every process the same scenario and --set options")

    def _on_alive(self, key: str, alive: bool) -> None:
        if self.link is not None:
            self.link.on_alive(keys.last_chunk(key), alive)
        name = keys.subsystem_of(keys.last_chunk(key), keys.AGENT_PREFIX)
        if name not in self.names:
            return
        if alive:
            self.alive.add(name)
            return
        self.alive.discard(name)
        self.ready.discard(name)
        if self.started and not self.finished:
            log.warning("coordinator: agent %s lost at step %d; applying its fallback", name, self.coordinator.k)
            self._carry_out(self.coordinator.on_agent_lost(name))

    def _on_plan(self, key: str, payload: bytes) -> None:
        name = keys.last_chunk(key)
        msg = self._decoded(name, payload)
        if msg is None:
            return
        if not isinstance(msg, PlanMessage) or msg.sender != name:
            self._reject(name, "not a plan from its key's agent")
            return
        self.messages.add(name, "plan", len(payload))
        actions, problem = self.coordinator.on_plan(msg)
        if problem is not None:
            if problem != STALE:  # late plans after a deadline are normal in realtime
                self._reject(name, problem)
            return
        self._carry_out(actions)

    def _on_setpoint(self, key: str, payload: bytes) -> None:
        """A setpoint request published on ``setpoint/<sender>``: answered on
        ``setpoint-answer/<sender>``."""
        self._setpoint_arrived(key, payload, partial(self._publish_answer, keys.setpoint_answer(self.run_id,
                                                                                                keys.last_chunk(key))))

    def _on_setpoint_query(self, key: str, payload: bytes, reply: Reply) -> None:
        """A setpoint request sent as a query on ``setpoint/<sender>``: answered by the query's one
        reply (a request dropped ends the query without a reply)."""
        self._setpoint_arrived(key, payload, reply)

    def _publish_answer(self, key: str, payload: bytes | None) -> None:
        if payload is not None:
            self.bus.publish(key, payload)

    def _setpoint_arrived(self, key: str, payload: bytes, respond: Reply) -> None:
        """A supervisory program's setpoint request on ``key``: answered through ``respond``, unless it
        does not decode or its sender is not its key's (then counted as dropped, and ``respond``
        told so with None).

        With a target worker, the request waits (behind those that arrived before it) until the
        targets it needs are known, and is taken and answered at the step boundary that follows.
        """
        sender = keys.last_chunk(key)
        msg = self._decoded(sender, payload)
        problem = None
        if msg is not None and (not isinstance(msg, Setpoint) or msg.sender != sender):
            problem = "not a setpoint request from its key's sender"
        elif msg is not None:
            try:
                keys.check_chunk(sender, "sender")
            except ValueError as exc:
                problem = str(exc)
        if problem is not None:
            self._reject(sender, problem)
        if msg is None or problem is not None:
            respond(None)
            return
        assert isinstance(msg, Setpoint)
        request = _Request(msg, respond)
        if self.targets is None:
            self._answer_setpoint(request, self.coordinator.on_setpoint(msg))
            return
        refusal = self.coordinator.setpoint_refusal(msg)  # refused now, it would be refused later too
        if refusal is None and self.finished:  # stopped early (a failure): its worker is gone
            refusal = self._refusal(msg, "the run is finished")
        if refusal is None and len(self._waiting) + len(self._batch) >= MAX_WAITING:
            refusal = self._refusal(msg, f"too many requests ({MAX_WAITING}) wait for their targets: ask again later")
        if refusal is not None:
            self._answer_setpoint(request, refusal)
            return
        self._waiting.append(request)
        if not self._batch:
            self._take_setpoints()

    def _take_setpoints(self) -> None:
        """Take every waiting request whose targets are known, in the order they arrived; send the
        others, with the targets they need, to the worker (one batch at a time)."""
        while self._waiting and not self._batch:
            requests = list(self._waiting)
            self._waiting.clear()
            self._try_to_take(requests)

    def _try_to_take(self, requests: list[_Request]) -> None:
        """Answer the refused ones of ``requests``; take the others now if every target they need is
        known, else make them the worker's batch."""
        refusals, unknown = self.coordinator.setpoint_needs([request.msg for request in requests])
        for request, refusal in zip(requests, refusals):
            if refusal is not None:
                self._answer_setpoint(request, refusal)
        taken = [request for request, refusal in zip(requests, refusals) if refusal is None]
        if not unknown:
            for request in taken:
                self._answer_setpoint(request, self.coordinator.on_setpoint(request.msg))
            return
        assert self.targets is not None
        self._batch = taken
        self.targets.submit(unknown, self._targets_known)

    def _targets_known(self, known: Known, error: str) -> None:
        """The worker computed the batch's targets (``known``), or could not (``error``): this is a
        step boundary, where the batch is taken (or its refusal sent), then the requests behind it."""
        batch, self._batch = self._batch, []
        if not batch:
            return  # the run stopped meanwhile: its requests were refused
        if error:
            for request in batch:
                self._answer_setpoint(request, self._refusal(request.msg, f"its target could not be computed: {error}"))
        else:
            self.coordinator.learn_targets(known)
            self._try_to_take(batch)  # a change of the schedule passed meanwhile may need more
        self._take_setpoints()

    def _refusal(self, msg: Setpoint, reason: str) -> SetpointAnswer:
        return SetpointAnswer(self.run_id, msg.id, msg.subsystem, False, -1, reason[:MAX_REASON])

    def _answer_setpoint(self, request: _Request, answer: SetpointAnswer) -> None:
        self._log_setpoint(request.msg, answer)
        request.respond(encode(answer))

    def _log_setpoint(self, msg: Setpoint, answer: SetpointAnswer) -> None:
        who = f"setpoint request {msg.id} from {_shown(msg.sender)} for subsystem {_shown(msg.subsystem)}"
        if answer.accepted:
            log.warning("coordinator: %s accepted from step %d", who, answer.k)
        else:
            log.warning("coordinator: %s refused: %s", who, _shown(answer.reason))

    def _on_kept(self, key: str, payload: bytes) -> None:
        name = keys.last_chunk(key)
        msg = self._decoded(name, payload)
        if msg is None:
            return
        if not isinstance(msg, Kept) or msg.sender != name:
            self._reject(name, "not a kept notice from its key's agent")
            return
        self.messages.add(name, "kept", len(payload))
        actions, problem = self.coordinator.on_kept(msg)
        if problem is not None:
            if problem != STALE:
                self._reject(name, problem)
            return
        self._carry_out(actions)

    @staticmethod
    def _log_refusal(refusal: PlanRefused) -> None:
        """Warn about an agent's first plan outside U_i; later ones are only counted."""
        if refusal.count == 1:
            log.warning("coordinator: refused the plan of agent %s at step %d round %d: its inputs leave U_%s by %.3g; "
                        "its fallback applies (further refusals are counted in summary.json, inputs_refused)",
                        refusal.name, refusal.k, refusal.round, refusal.name, refusal.excess)

    # ------------------------------------------------------------------ act
    def _maybe_start(self) -> None:
        if not self.started and self.ready >= set(self.names) and (self.link is None or self.x0 is not None):
            self.started = True
            self._t0 = self.bus.now()
            x0 = self.x0
            self._carry_out(self.coordinator.start(None if x0 is None else x0.x, None if x0 is None else x0.y))

    def _on_measured(self, k: int, measured: Measurement) -> None:
        """The plant outside measured x(k) (complete; or, in part, the outputs y(k))."""
        if not self.started:
            self.x0 = measured
            self._maybe_start()
        elif not self.finished:
            self._carry_out(self.coordinator.on_state(k, measured.x, measured.y))

    def present(self) -> bool:
        """True while an agent, or a plant outside, still holds its liveliness token."""
        return bool(self.alive) or (self.link is not None and any(self.link.alive.values()))

    def startup_failure(self, timeout: float) -> str:
        """Why the run did not start within ``timeout`` s: the agents (and plant) missing, the
        designs and protocol versions that differ."""
        missing = sorted(set(self.names) - self.ready)
        parts = []
        if missing:
            parts.append(f"agents {', '.join(missing)} not ready within {timeout:g} s "
                         f"(alive: {', '.join(sorted(self.alive)) or 'none'}; run id '{self.run_id}')")
        if self.link is not None and self.x0 is None:
            parts.append(self.link.describe_missing(0, f"within {timeout:g} s"))
        versions = self.version_mismatch()
        mismatch = self.design_mismatch(missing)
        return f"{self.who}: " + "; ".join(([versions] if versions else []) + ([mismatch] if mismatch else []) + parts)

    def version_mismatch(self) -> str:
        """Which agents spoke another protocol version ("" if none)."""
        if not self.other_versions:
            return ""
        said = [f"agent {name} speaks {'no protocol version' if v is None else f'protocol version {v}'}"
                for name, v in sorted(self.other_versions.items())[:NAMED_DESIGNS]]
        return f"{'; '.join(said)}; this coordinator speaks protocol version {PROTOCOL_VERSION}"

    def _carry_out(self, actions: list) -> None:
        # build and write the records after the next releases are out
        completed = [action for action in actions if isinstance(action, StepCompleted)]
        try:
            self._dispatch([a for a in actions if not isinstance(a, StepCompleted)])
        finally:
            for action in completed:
                rec = action.record
                self.on_step(rec)
                if self.telemetry is not None:
                    self.telemetry.step(rec, self)

    def _dispatch(self, actions: list) -> None:
        for n, action in enumerate(actions):
            if isinstance(action, SendRelease):
                rel = action.release
                if self.mode == "realtime" and rel.round == 0 and rel.k > 0:
                    wait = self._t0 + rel.k * self.dt - self.bus.now()
                    if wait > 0:
                        self.bus.call_later(wait, partial(self._dispatch, actions[n:]))
                        return
                if rel.round == 0:
                    self._open_step(rel.k)  # the step's time includes sending its release
                self.bus.publish(keys.release(self.run_id), encode(rel))
            elif isinstance(action, RoundOpened):
                if action.round == 0 and self._opened_step != action.k:
                    self._open_step(action.k)  # no release (every agent lost)
                if self.deadline is not None:
                    self.bus.call_later(self.deadline, partial(self._deadline_passed, action.k, action.round))
            elif isinstance(action, ApplyInputs):
                assert self.link is not None  # a coordinator applies its inputs through a link only to a plant outside
                self.link.apply(action.k, action.u)
            elif isinstance(action, PlanRefused):
                self._log_refusal(action)
            elif isinstance(action, RunFinished):
                self._stop(action.reason)

    def _deadline_passed(self, k: int, r: int) -> None:
        self._carry_out(self.coordinator.on_deadline(k, r))

    def _open_step(self, k: int) -> None:
        self.coordinator.step_opened()
        self._opened_step = k

    def _stop(self, reason: str) -> None:
        self.finished = True
        if self.link is not None:
            self.link.stop()
        waiting = self._batch + list(self._waiting)
        self._batch, self._waiting = [], deque()
        for request in waiting:  # never left without an answer
            self._answer_setpoint(request, self._refusal(request.msg, "the run is finished"))
        if self.targets is not None:
            self.targets.close()
        msg = Stop(run=self.run_id, k=self.coordinator.k, reason=reason[:MAX_REASON])
        self._stop_payload = encode(msg)
        self.bus.publish(keys.control(self.run_id), self._stop_payload)

    def repeat_stop(self) -> None:
        """Send the run's ``Stop`` again (agents ignore copies): a lost one must not leave an agent
        to find the plant gone instead of the run finished."""
        if self._stop_payload is not None:
            self.bus.publish(keys.control(self.run_id), self._stop_payload)

    def fail(self, reason: str) -> None:
        """Abort the run: tell every agent and stop.

        Parameters
        ----------
        reason : str
            Why the run failed: kept as ``failure`` and sent in the ``Stop`` as ``failed: <reason>``
            (cut to the message's longest reason). Nothing happens once the run is over.
        """
        if not self.finished:
            self.failure = reason
            self._stop(f"failed: {reason}")

    def abort(self, reason: str = "aborted") -> None:
        """End the run early: tell every agent and stop.

        Parameters
        ----------
        reason : str
            Kept as ``failure`` and sent as the ``Stop``'s reason as it is (cut to the message's
            longest reason). Nothing happens once the run is over.
        """
        if not self.finished:
            self.failure = reason
            self._stop(reason)
