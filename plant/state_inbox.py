"""The coordinator's inbox for measured states from an outside plant (no bus, no clock).

An outside plant reports x(k) whole (as ``plant``) or per subsystem (``sensor-I`` reports
subsystem I); in a run with estimation, a subsystem's measured outputs y_i(k) may come in place
of its state. The inbox assembles step k's measurement from what arrives, accepts each
subsystem's first valid entry, and says what is wrong with anything else, so that a run stopped
for want of a state can name the sensor and the reason.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmpc.bus import keys
from dmpc.bus.messages import State
from dmpc.core.system import CoupledSystem
from dmpc.security.rejects import MAX_MAGNITUDE, STALE


@dataclass(frozen=True)
class Measurement:
    """What an outside plant reported of one step.

    Attributes
    ----------
    x : ndarray, shape (n,)
        The state, NaN in the subsystems that reported their outputs instead.
    y : dict name -> ndarray, shape (p_i,)
        The outputs of those subsystems (empty: every state was reported).
    """

    x: np.ndarray
    y: dict[str, np.ndarray]


class StateInbox:
    """Collects x(k) (or, per subsystem, y_i(k)) for one step at a time.

    Parameters
    ----------
    system : CoupledSystem
    outputs : bool
        The run estimates its state (``estimation``): a subsystem may report its outputs y_i
        instead of its state; without, an output is refused.
    """

    def __init__(self, system: CoupledSystem, outputs: bool = False) -> None:
        self.system = system
        self.outputs = outputs
        self.names = [s.name for s in system.subsystems]
        self._n = {s.name: s.n for s in system.subsystems}
        self._p = {s.name: s.p for s in system.subsystems}
        self.k: int | None = None  # the step whose state is awaited
        self.done = -1  # the last step whose state was complete
        self._parts: dict[str, np.ndarray] = {}
        self._outputs: dict[str, np.ndarray] = {}
        self.last_problem: dict[str, str] = {}  # per source: the last reason one of its states was dropped
        self.duplicates = 0

    def expect(self, k: int) -> None:
        """Await the state of step ``k`` (earlier parts are dropped)."""
        self.k = k
        self._parts = {}
        self._outputs = {}

    def missing(self) -> list[str]:
        """The subsystems whose state (or outputs) for the awaited step has not arrived."""
        return [name for name in self.names if name not in self._parts and name not in self._outputs]

    def problem(self, source: str, msg: State) -> str | None:
        """None if ``msg`` from ``source`` (its key's last chunk) is usable for the awaited step."""
        if msg.sender != source:
            return f"sender {msg.sender!r} does not match its key's {source!r}"
        allowed = None
        if source != keys.PLANT_ROLE:
            name = keys.subsystem_of(source, keys.SENSOR_PREFIX)
            if name is None or name not in self._n:
                return f"{source!r} is neither the plant nor a subsystem's sensor"
            allowed = name
        if msg.y and not self.outputs:
            return "outputs (y) in a run without estimation: this run needs every subsystem's state x"
        for what, parts, sizes in (("state", msg.x, self._n), ("outputs", msg.y, self._p)):
            for name, x in parts.items():
                if name not in sizes:
                    return f"unknown subsystem {name!r}"
                if allowed is not None and name != allowed:
                    return f"a sensor of {allowed} sent the {what} of {name}"
                has, is_ = ("has", "is") if what == "state" else ("have", "are")
                if x.shape != (sizes[name],):
                    return f"the {what} of subsystem {name} {has} shape {x.shape}, expected ({sizes[name]},)"
                if x.size and float(np.abs(x).max()) > MAX_MAGNITUDE:
                    return f"the {what} of subsystem {name} {is_} out of range (beyond {MAX_MAGNITUDE:g})"
        if msg.k <= self.done:
            return STALE  # a copy of a state already taken (the plant repeats x(0), answers repeats)
        if msg.k != self.k:
            return f"state of step {msg.k} not awaited"
        return None

    def take(self, msg: State) -> Measurement | None:
        """Take a message ``msg`` that :meth:`problem` found usable; returns the step's measurement once
        every subsystem's state or outputs are in (each subsystem's first entry counts)."""
        for parts, given in ((self._parts, msg.x), (self._outputs, msg.y)):
            for name, value in given.items():
                if name in self._parts or name in self._outputs:
                    self.duplicates += 1
                else:
                    parts[name] = value
        if len(self._parts) + len(self._outputs) < len(self.names):
            return None
        x = np.concatenate([self._parts[name] if name in self._parts else np.full(self._n[name], np.nan)
                            for name in self.names])
        measured = Measurement(x, {name: self._outputs[name] for name in self.names if name in self._outputs})
        assert self.k is not None  # a state taken is of the awaited step (problem() is None)
        self.done = self.k
        self.k = None
        self._parts = {}
        self._outputs = {}
        return measured

    def owners(self, names: list[str]) -> list[str]:
        """The sources that could report the subsystems ``names``: the plant and their sensors."""
        return keys.state_sources(names)
