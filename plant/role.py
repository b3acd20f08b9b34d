"""The plant role on a bus: applies each step's inputs and answers with the measured state.

This is dmpc's own simulated plant speaking the plant's side of the protocol (docs/protocol.md,
"The plant's side"), for ``dmpc plant --coordinator external``. It reports the whole state as
``plant``, or only some subsystems' states, one ``sensor-I`` per subsystem, as separate sensors
on one machine each would; with ``outputs``, each subsystem that measures less than its state
(a C other than the identity) reports its outputs y_i = C_i x_i instead, as its sensors would.
With an operating point it speaks the plant's own units, as an outside plant does.

The rules it follows are the ones any outside plant must follow:

- the state x(0) is sent every ``repeat`` seconds until the inputs of step 0 arrive;
- ``Inputs`` of step k (the one expected) is applied once, and x(k+1) sent;
- a repeated ``Inputs`` of the step just applied is answered with the same x(k+1) again;
- a ``Stop`` ends it.
"""
from __future__ import annotations

import logging
from typing import TypeVar

import numpy as np

from dmpc.bus import keys
from dmpc.bus.codec import DecodeError, decode, encode
from dmpc.bus.interface import Bus, Timer
from dmpc.bus.messages import COORDINATOR, Inputs, State, Stop
from dmpc.core.system import CoupledSystem
from dmpc.security.rejects import Rejections

_FromCoordinator = TypeVar("_FromCoordinator", Inputs, Stop)  # what the coordinator sends the plant

log = logging.getLogger("dmpc.plant")
REPEAT = 0.5


class PlantRole:
    """A simulated plant (or some of its sensors) on a bus.

    Parameters
    ----------
    bus : Bus
    plant : object with ``x`` (ndarray, shape (n,)) and ``step(u) -> x_next``
        The simulated dynamics (:func:`dmpc.plant.models.make_plant`).
    system : CoupledSystem
        For the subsystems' names and the state and input slices.
    run_id : str
    sensors : list of str, optional
        Report only these subsystems, each as its own ``sensor-<name>``; None reports the
        whole state as ``plant``.
    repeat : float
        Seconds between copies of x(0) until step 0's inputs arrive.
    outputs : bool
        Report the outputs y_i = C_i x_i of the subsystems whose C is not the identity, not their
        states (a run with estimation).
    """

    def __init__(self, bus: Bus, plant, system: CoupledSystem, run_id: str, sensors: list[str] | None = None,
                 repeat: float = REPEAT, outputs: bool = False) -> None:
        self.bus = bus
        self.plant = plant
        self.system = system
        self.run_id = run_id
        self.names = [s.name for s in system.subsystems]
        self.sensors = sensors
        self.repeat = repeat
        self._measures = {s.name: s.C for s in system.subsystems if outputs and s.C is not None}
        self.k = 0  # the step whose state was sent last
        self.stopped = False
        self.stop_reason = ""
        self.coordinator_seen = False
        self.coordinator_lost = False
        self.rejects = Rejections(log, "plant", bus.now, [COORDINATOR])
        self._timer: Timer | None = None
        self._m = {name: system.subsystems[i].m for i, name in enumerate(self.names)}
        bus.subscribe(keys.inputs(run_id), self._on_inputs, hot=True)
        bus.subscribe(keys.control(run_id), self._on_control)
        bus.watch_alive(keys.alive(run_id, keys.COORDINATOR_ROLE), self._on_alive)

    @property
    def roles(self) -> list[str]:
        """The roles this process reports as."""
        if self.sensors is None:
            return [keys.PLANT_ROLE]
        return [keys.sensor_role(name) for name in self.sensors]

    def announce(self) -> None:
        """Hold the roles' liveliness tokens and send x(0) until step 0's inputs arrive."""
        for role in self.roles:
            self.bus.declare_alive(keys.alive(self.run_id, role))
        self._send_first()

    def _send_first(self) -> None:
        self._timer = None
        if self.k > 0 or self.stopped:
            return
        self._send_state()
        self._timer = self.bus.call_later(self.repeat, self._send_first)

    def _send_state(self) -> None:
        x = np.asarray(self.plant.x, dtype=float)
        if self.system.has_operating_point:
            x = x + self.system.state_offset  # the wire is in the plant's units
        by_name = dict(zip(self.names, self.system.split_state(x)))
        for role, names in ([(keys.PLANT_ROLE, self.names)] if self.sensors is None else
                            [(keys.sensor_role(name), [name]) for name in self.sensors]):
            states = {name: by_name[name] for name in names if name not in self._measures}
            outputs = {name: self._measures[name] @ by_name[name] for name in names if name in self._measures}
            msg = State(run=self.run_id, k=self.k, sender=role, x=states, y=outputs)
            self.bus.publish(keys.state(self.run_id, role), encode(msg))

    def _decode(self, payload: bytes, expected: type[_FromCoordinator]) -> _FromCoordinator | None:
        try:
            msg = decode(payload)
        except DecodeError as exc:
            self.rejects(COORDINATOR, str(exc))
            return None
        if not isinstance(msg, expected) or msg.run != self.run_id or msg.sender != COORDINATOR:
            self.rejects(COORDINATOR, f"not a {expected.__name__} of this run from the coordinator")
            return None
        return msg

    def _on_inputs(self, key: str, payload: bytes) -> None:
        msg = self._decode(payload, Inputs)
        if msg is None or self.stopped:
            return
        if msg.k == self.k - 1:
            self._send_state()  # the coordinator did not get x(k+1): the same answer again
            return
        if msg.k != self.k:
            self.rejects(COORDINATOR, f"inputs of step {msg.k} while at step {self.k}")
            return
        problem = self._input_problem(msg)
        if problem:
            self.rejects(COORDINATOR, problem)
            return
        u = np.concatenate([np.asarray(msg.u[name], dtype=float) for name in self.names])
        if self.system.has_operating_point:
            u = u - self.system.input_offset
        self.plant.step(u)
        self.k += 1
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._send_state()

    def _input_problem(self, msg: Inputs) -> str:
        if list(msg.u) != self.names:
            return "inputs: expected one entry per subsystem, in the scenario's order"
        for name, u in msg.u.items():
            if u.shape != (self._m[name],):
                return f"inputs of {name}: shape {u.shape}, expected ({self._m[name]},)"
        return ""

    def _on_control(self, key: str, payload: bytes) -> None:
        msg = self._decode(payload, Stop)
        if msg is not None:
            self.stopped = True
            self.stop_reason = msg.reason

    def _on_alive(self, key: str, alive: bool) -> None:
        if alive:
            self.coordinator_seen = True
            self.coordinator_lost = False
        elif self.coordinator_seen:
            self.coordinator_lost = True
