"""Setpoint targets computed beside the run: a thread of the coordinator's process.

A setpoint request that arrives while the run goes on needs the targets of the requests it makes
(a steady-state QP each, :class:`~dmpc.tracking.targets.TargetSpace`). Computed on the run's
thread, they would stretch the step that takes the request. Here they are computed on a thread of
their own, which loads the solver and builds the QPs' matrices as soon as the node is made, and
each result is handed back to the run's thread (the bus's ``call_later``), where the coordinator
takes the request at the next step boundary (docs/protocol.md, "Setpoints while a run goes on").

The coordinator and the tracker stay pure and single-threaded: this module is the only one with
a thread, and it only calls :meth:`TargetSpace.target <dmpc.tracking.targets.TargetSpace.target>`,
which reads the space and writes nothing the run's thread reads.
"""
from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from functools import partial

from dmpc.bus.interface import Bus
from dmpc.tracking.targets import Request, Target, TargetSpace

log = logging.getLogger("dmpc.plant")

Known = list[tuple[Request, Target]]
Done = Callable[[Known, str], None]
"""Called on the run's thread with the targets computed (request, target) and "" , or with none and
why they could not be computed."""


class TargetWorker:
    """Computes setpoint targets on a thread of its own and hands them to the bus's thread.

    Parameters
    ----------
    space : TargetSpace
        The run's steady states (the tracker's ``space``).
    bus : Bus
        The node's bus; its :meth:`~dmpc.bus.interface.Bus.call_later` must be callable from any
        thread (``call_later_threadsafe``).
    """

    def __init__(self, space: TargetSpace, bus: Bus) -> None:
        if not bus.call_later_threadsafe:
            raise ValueError("a target worker needs a bus whose call_later may be called from any thread")
        self.space = space
        self.bus = bus
        self._jobs: queue.SimpleQueue[tuple[list[Request], Done] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._work, name="dmpc-targets", daemon=True)
        self._thread.start()

    def submit(self, requests: list[Request], done: Done) -> None:
        """Compute the targets of ``requests``, then call ``done(known, error)`` on the bus's thread.

        Parameters
        ----------
        requests : list of Request
            The requests whose targets are wanted, in the order they are computed.
        done : callable (known, error) -> None
            Called once, on the thread that runs the bus: ``known`` the (request, target) pairs
            and ``error`` "", or no pairs and why the targets could not be computed.
        """
        self._jobs.put((list(requests), done))

    def _work(self) -> None:
        try:
            self.space.load()
        except Exception as exc:  # noqa: BLE001 - a thread's last resort: the first target says it again
            log.warning("coordinator: loading the setpoint targets' solver failed: %s", exc)
        while True:
            job = self._jobs.get()
            if job is None:
                return
            requests, done = job
            try:
                known: Known = [(request, self.space.target(request)) for request in requests]
                error = ""
            except Exception as exc:  # noqa: BLE001 - the request is refused with the reason, the run goes on
                known, error = [], f"{type(exc).__name__}: {exc}"
            try:
                self.bus.call_later(0.0, partial(done, known, error))
            except Exception:  # noqa: BLE001 - the bus is closed: the run is over
                return

    def close(self) -> None:
        """Let the thread end once the job it works on is done (idempotent; it never blocks)."""
        self._jobs.put(None)
