"""The coordinator's link to an outside plant: sends each step's inputs, gathers the measured state.

docs/protocol.md, "The plant's side": the coordinator publishes ``Inputs`` of step k on
``dmpc/<run>/inputs`` and re-sends it every ``REPEAT`` seconds until x(k+1) is complete (a copy
may be lost; the plant answers a repeat without applying it twice). States come on
``dmpc/<run>/state/<source>``, whole from ``plant`` or per subsystem from ``sensor-<name>``.
If x(k+1) is not complete within ``timeout`` seconds the link reports a failure naming the
missing subsystems, their sources' liveliness and the last reason a state of theirs was dropped.
"""
from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np

from dmpc.bus import keys
from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.interface import Bus, Timer
from dmpc.bus.messages import Inputs, State
from dmpc.core.system import CoupledSystem
from dmpc.plant.state_inbox import Measurement, StateInbox
from dmpc.security.rejects import STALE, Rejections

REPEAT = 0.5
MAX_NAMED = 4  # missing subsystems spelt out in a failure


class PlantLink:
    """Inputs out, states in, for one run.

    Parameters
    ----------
    bus : Bus
    system : CoupledSystem
    run_id : str
    rejects : Rejections
        Where dropped states are counted, per source.
    on_state : callable (k, Measurement) -> None
        Called with the measurement of step k once it is complete: x(k), shape (n,), NaN in the
        subsystems that reported their outputs y_i(k) instead (a run with ``outputs``).
    on_failure : callable str -> None
        Called once if a state does not come in time.
    timeout : float
        Seconds to wait for x(k+1) after sending the inputs of step k.
    outputs : bool
        The run estimates its state: a subsystem may report its outputs in place of its state.

    With an operating point (the subsystems' ``x_op``, ``u_op``) the wire is in the plant's own
    units: the inputs go out as u_op + u, and x_op (C x_op for outputs) is taken from what comes in.
    """

    def __init__(self, bus: Bus, system: CoupledSystem, run_id: str, rejects: Rejections,
                 on_state: Callable[[int, Measurement], None], on_failure: Callable[[str], None],
                 timeout: float = 10.0, outputs: bool = False) -> None:
        self.bus = bus
        self.system = system
        self.run_id = run_id
        self.rejects = rejects
        self.inbox = StateInbox(system, outputs)
        self.names = self.inbox.names
        self.on_state = on_state
        self.on_failure = on_failure
        self.timeout = timeout
        self.alive: dict[str, bool] = {}  # per source role: its liveliness token is up
        self._inputs: bytes | None = None
        self._repeat: Timer | None = None
        self._deadline: Timer | None = None
        self._stopped = False
        self._sources = frozenset(self.sources)
        self._operating_outputs = {s.name: s.operating_output for s in system.subsystems}  # C_i x_op, per subsystem
        bus.subscribe(keys.state_prefix(run_id), self._on_state)  # not hot: the plans are (one hot wait)

    @property
    def sources(self) -> list[str]:
        """Every role that may send states."""
        return self.inbox.owners(self.names)

    def await_first(self) -> None:
        """Await x(0) (the plant repeats it until step 0's inputs; no deadline: the start-up's)."""
        self.inbox.expect(0)

    def apply(self, k: int, u: np.ndarray) -> None:
        """Send u(k) (shape (m,)) and await x(k+1)."""
        if self.system.has_operating_point:
            u = u + self.system.input_offset
        parts = {name: u[self.system.us(i)] for i, name in enumerate(self.names)}
        self._inputs = encode(Inputs(run=self.run_id, k=k, u=parts))
        self.inbox.expect(k + 1)
        self._send()
        self._deadline = self.bus.call_later(self.timeout, partial(self._late, k + 1))

    def stop(self) -> None:
        """No more repeats or deadlines (the run is over)."""
        self._stopped = True
        self._cancel()

    def _send(self) -> None:
        self._repeat = None
        if self._inputs is None or self._stopped:
            return
        self.bus.publish(keys.inputs(self.run_id), self._inputs)
        self._repeat = self.bus.call_later(REPEAT, self._send)

    def _cancel(self) -> None:
        for timer in (self._repeat, self._deadline):
            if timer is not None:
                timer.cancel()
        self._repeat = self._deadline = None
        self._inputs = None

    def _on_state(self, key: str, payload: bytes) -> None:
        source = keys.last_chunk(key)
        if source not in self._sources:
            self.rejects(source, "state from a source that is neither the plant nor a subsystem's sensor")
            return
        try:
            msg = decode(payload)
        except DecodeError as exc:
            self._drop(source, str(exc))
            return
        if not isinstance(msg, State) or msg.run != self.run_id:
            self._drop(source, "not a state of this run")
            return
        problem = self.inbox.problem(source, msg)
        if problem is not None:
            if problem != STALE:  # copies of the last state are normal after a repeat
                self._drop(source, problem)
            return
        k = self.inbox.k
        measured = self.inbox.take(msg)
        if measured is not None and k is not None and not self._stopped:  # k: the awaited step, a state was taken
            self._cancel()
            self.on_state(k, self._around_operating_point(measured))

    def _around_operating_point(self, measured: Measurement) -> Measurement:
        """``measured`` (in the plant's units) in the model's deviations from the operating point."""
        if not self.system.has_operating_point:
            return measured
        outputs = {name: y - self._operating_outputs[name] for name, y in measured.y.items()}
        return Measurement(measured.x - self.system.state_offset, outputs)

    def _drop(self, source: str, why: str) -> None:
        """Count a dropped state and keep why, to name it if the step's state never completes."""
        self.inbox.last_problem[source] = why
        self.rejects(source, why)

    def on_alive(self, role: str, alive: bool) -> None:
        """The liveliness token of ``role`` appeared (``alive``) or went (the host watches every token)."""
        if role in self._sources:
            self.alive[role] = alive

    def _late(self, k: int) -> None:
        if self._stopped or self.inbox.k != k:
            return
        self._cancel()
        self.on_failure(self.describe_missing(k, f"within {self.timeout:g} s"))

    def describe_missing(self, k: int, when: str) -> str:
        """Why x(k) is not complete ``when`` (e.g. "within 2 s"): the missing subsystems, their
        sources and what was wrong."""
        missing = self.inbox.missing()
        shown = ", ".join(missing[:MAX_NAMED]) + (f" and {len(missing) - MAX_NAMED} more" if len(missing) > MAX_NAMED
                                                  else "")
        facts = []
        for source in self.inbox.owners(missing[:MAX_NAMED]):
            state = self.alive.get(source)
            problem = self.inbox.last_problem.get(source)
            if state is None and problem is None:
                continue
            said = [] if state is None else ["alive" if state else "its token is gone"]
            if problem:
                said.append(f"last state dropped: {problem}")
            facts.append(f"{source}: {'; '.join(said)}")
        if not any(self.alive.get(s) is not None for s in self.sources):
            facts.append("no plant or sensor seen alive")
        detail = f" ({'; '.join(facts)})" if facts else ""
        return f"the plant sent no state for step {k} {when} (missing: subsystems {shown}){detail}"
