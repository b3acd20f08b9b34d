"""Every node of a run in one process, on the in-memory bus (``dmpc simulate``).

The ``centralized`` method has no nodes: :func:`record_run` runs it as one QP per step
(dmpc.runtime.central_loop) and records it the same way.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from dmpc.agents.node import AgentNode
from dmpc.agents.process import agent_node
from dmpc.bus.faults import PLANT_PROCESS, FaultyBus
from dmpc.bus.interface import Bus
from dmpc.bus.memory import MemoryBus
from dmpc.coordinator.node import CoordinatorNode
from dmpc.coordinator.process import coordinator_node
from dmpc.core.steps import StepRecord
from dmpc.methods import method_spec
from dmpc.plant.models import make_plant
from dmpc.prepared import Prepared
from dmpc.records.session import RunRecorder
from dmpc.runtime.central_loop import CentralLoop


@dataclass
class InProcessRun:
    """The nodes of one in-process run (exposed for tests that inject faults): the in-memory ``bus``, the
    ``coordinator``'s node and the ``agents``' nodes."""

    bus: MemoryBus
    coordinator: CoordinatorNode
    agents: list[AgentNode]


def build_run(prepared: Prepared, on_step: Callable[[StepRecord], None], run_id: str = "local",
              bus_for: Callable[[MemoryBus, str], Bus] | None = None) -> InProcessRun:
    """Create the bus, the coordinator's node and one agent node per subsystem of the ``prepared``
    run ``run_id``; ``on_step`` sees every step as it completes.

    Parameters
    ----------
    bus_for : callable (bus, node name) -> Bus, optional
        Wraps the shared bus per node (fault injection); identity by default.
    """
    bus = MemoryBus()
    if bus_for is not None:
        view = bus_for
    elif prepared.faults.is_clean:
        view = lambda b, name: b
    else:
        view = lambda b, name: FaultyBus(b, name, prepared.faults)
    node = coordinator_node(prepared, view(bus, PLANT_PROCESS), run_id, on_step, make_plant(prepared))
    agents = [agent_node(prepared, name, view(bus, name), run_id) for name in prepared.names]
    node.announce()
    for agent in agents:
        agent.announce()
    return InProcessRun(bus=bus, coordinator=node, agents=agents)


def simulate(prepared: Prepared, on_step: Callable[[StepRecord], None], run_id: str = "local",
             bus_for: Callable[[MemoryBus, str], Bus] | None = None, startup_timeout: float = 60.0) -> InProcessRun:
    """Run the ``prepared`` run ``run_id`` to the end in this process; ``on_step`` sees every step as
    it completes; ``bus_for`` as for :func:`build_run`.

    ``startup_timeout`` is in simulated seconds: agents whose Ready never gets through (a dead
    link) fail the run instead of retrying forever.
    """
    run = build_run(prepared, on_step, run_id, bus_for)
    if not run.bus.run(until=lambda: run.coordinator.started or run.coordinator.finished, timeout=startup_timeout):
        missing = sorted(set(prepared.names) - run.coordinator.ready)
        run.coordinator.fail(f"agents {', '.join(missing)} not ready within {startup_timeout:g} s of simulated time")
        return run
    finished = run.bus.run(until=lambda: run.coordinator.finished)
    if not finished:
        run.coordinator.fail("the in-memory run stalled (no events left before the last step)")
    return run


def record_run(prepared: Prepared, recorder: RunRecorder) -> tuple[dict, str]:
    """Run the prepared method in this process into the RunRecorder ``recorder`` and complete its records.

    Distributed methods run their nodes on the in-memory bus (:func:`simulate`); ``centralized``
    runs one QP per step. Returns the summary and the failure ("" if none).
    """
    if not method_spec(prepared.method).distributed:
        loop = CentralLoop(prepared.system, prepared.design, setpoints=prepared.setpoints,
                           setpoint_margin=prepared.setpoint_margin)
        result = loop.run(prepared.protocol.steps, recorder.on_step, plant=make_plant(prepared))
        summary = recorder.complete(runtime="in-process (centralized, no agents)", failure=result.failure or None)
        return summary, result.failure
    run = simulate(prepared, recorder.on_step)
    summary = recorder.complete(runtime="in-process", failure=run.coordinator.failure or None,
                                agents={a.name: a.report() for a in run.agents}, **run.coordinator.counts())
    return summary, run.coordinator.failure
