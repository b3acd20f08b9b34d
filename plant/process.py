"""``dmpc plant``: the plant simulator and step barrier as a process on the Zenoh bus."""
from __future__ import annotations

from dataclasses import dataclass

from dmpc.bus.interface import Bus
from dmpc.methods import terminal_policy
from dmpc.plant.barrier import Coordinator
from dmpc.plant.dynamics import Plant
from dmpc.plant.node import PlantNode
from dmpc.records.session import RunRecorder
from dmpc.runtime.setup import Prepared

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130
LINGER = 2.0
STOP_REPEAT = 0.2


@dataclass(frozen=True)
class PlantOutcome:
    code: int
    message: str
    summary: dict | None


def run_plant(prepared: Prepared, recorder: RunRecorder, bus: Bus, run_id: str, startup_timeout: float,
              runtime: str = "multi-process") -> PlantOutcome:
    """Wait for every agent, step the run to the end, write the records.

    Ctrl-C (or SIGTERM) stops the agents and keeps every completed step in the run folder.
    """
    policy = terminal_policy(prepared.method, prepared.system, prepared.design)
    coordinator = Coordinator(prepared.system, prepared.design, Plant(prepared.system), prepared.protocol, run_id,
                              policy=policy)
    node = PlantNode(bus, coordinator, prepared.digest, recorder.on_step, mode=prepared.mode, dt=prepared.dt,
                     deadline=prepared.deadline)
    node.announce()
    try:
        if not bus.run(until=lambda: node.started or node.finished, timeout=startup_timeout):
            missing = sorted(set(prepared.names) - node.ready)
            alive = sorted(node.alive)
            reason = (f"plant: agents {', '.join(missing)} not ready within {startup_timeout:g} s "
                      f"(alive: {', '.join(alive) or 'none'}; run id '{run_id}')")
            node.fail(reason)
            summary = recorder.complete(runtime=runtime, failure=reason)
            linger(bus, node)
            return PlantOutcome(EXIT_FAILED, reason, summary)
        bus.run(until=lambda: node.finished)
    except KeyboardInterrupt:
        node.abort("aborted")
        summary = recorder.complete(runtime=runtime, aborted="interrupted", rejected=node.rejected,
                                    rejected_reasons=node.rejects.reasons)
        linger(bus, node)
        return PlantOutcome(EXIT_INTERRUPTED, f"plant: interrupted after {coordinator.k} steps", summary)
    summary = recorder.complete(runtime=runtime, failure=node.failure or None, rejected=node.rejected,
                                rejected_reasons=node.rejects.reasons, duplicates=coordinator.duplicates)
    linger(bus, node)
    if node.failure:
        return PlantOutcome(EXIT_FAILED, f"plant: {node.failure}", summary)
    return PlantOutcome(EXIT_OK, f"plant: finished {coordinator.k} steps", summary)


def linger(bus: Bus, node: PlantNode, timeout: float = LINGER) -> None:
    """Keep the session open until the agents, told to stop, have left (at most ``timeout`` s).

    Closing at once could withdraw the plant's liveliness token before the Stop message has
    reached every agent (through a router they travel different paths), and an agent would
    then report a lost plant instead of a finished run. Stop is repeated every
    ``STOP_REPEAT`` s meanwhile, in case a copy was lost (injected loss drops it too).
    """
    end = bus.now() + timeout
    try:
        while node.alive and bus.now() < end:
            if not bus.run(until=lambda: not node.alive, timeout=min(STOP_REPEAT, end - bus.now())):
                node.repeat_stop()
    except KeyboardInterrupt:
        pass
