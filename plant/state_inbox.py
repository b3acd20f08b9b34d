"""The coordinator's inbox for measured states from an outside plant (no bus, no clock).

An outside plant reports x(k) whole (as ``plant``) or per subsystem (``sensor-I`` reports
subsystem I). The inbox assembles step k's state from what arrives, accepts each subsystem's
first valid entry, and says what is wrong with anything else, so that a run stopped for want
of a state can name the sensor and the reason.
"""
from __future__ import annotations

import numpy as np

from dmpc.bus import keys
from dmpc.bus.messages import State
from dmpc.core.system import CoupledSystem
from dmpc.security.rejects import MAX_MAGNITUDE, STALE


class StateInbox:
    """Collects x(k) for one step at a time.

    Parameters
    ----------
    system : CoupledSystem
    """

    def __init__(self, system: CoupledSystem) -> None:
        self.system = system
        self.names = [s.name for s in system.subsystems]
        self._n = {s.name: s.n for s in system.subsystems}
        self.k: int | None = None  # the step whose state is awaited
        self.done = -1  # the last step whose state was complete
        self._parts: dict[str, np.ndarray] = {}
        self.last_problem: dict[str, str] = {}  # per source: the last reason one of its states was dropped
        self.duplicates = 0

    def expect(self, k: int) -> None:
        """Await the state of step ``k`` (earlier parts are dropped)."""
        self.k = k
        self._parts = {}

    def missing(self) -> list[str]:
        """The subsystems whose state for the awaited step has not arrived."""
        return [name for name in self.names if name not in self._parts]

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
        for name, x in msg.x.items():
            if name not in self._n:
                return f"unknown subsystem {name!r}"
            if allowed is not None and name != allowed:
                return f"a sensor of {allowed} sent the state of {name}"
            if x.shape != (self._n[name],):
                return f"the state of subsystem {name} has shape {x.shape}, expected ({self._n[name]},)"
            if x.size and float(np.abs(x).max()) > MAX_MAGNITUDE:
                return f"the state of subsystem {name} is out of range (beyond {MAX_MAGNITUDE:g})"
        if msg.k <= self.done:
            return STALE  # a copy of a state already taken (the plant repeats x(0), answers repeats)
        if msg.k != self.k:
            return f"state of step {msg.k} not awaited"
        return None

    def take(self, msg: State) -> np.ndarray | None:
        """Take a message ``msg`` that :meth:`problem` found usable; returns x(k), shape (n,), once every
        subsystem's state is in (each subsystem's first entry counts)."""
        for name, x in msg.x.items():
            if name in self._parts:
                self.duplicates += 1
            else:
                self._parts[name] = x
        if len(self._parts) < len(self.names):
            return None
        x = np.concatenate([self._parts[name] for name in self.names])
        assert self.k is not None  # a state taken is of the awaited step (problem() is None)
        self.done = self.k
        self.k = None
        self._parts = {}
        return x

    def owners(self, names: list[str]) -> list[str]:
        """The sources that could report the subsystems ``names``: the plant and their sensors."""
        return keys.state_sources(names)
