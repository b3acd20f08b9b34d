"""Every node of a run in one process, on the in-memory bus (``dmpc simulate``).

The ``centralized`` method has no nodes: :func:`record_run` runs it as one QP per step
(dmpc.runtime.central_loop) and records it the same way.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from dmpc.agents.controller import AgentController
from dmpc.agents.node import AgentNode
from dmpc.bus.faults import PLANT_PROCESS, FaultyBus
from dmpc.bus.interface import Bus
from dmpc.bus.memory import MemoryBus
from dmpc.methods import method_spec, terminal_policy
from dmpc.plant.barrier import Coordinator
from dmpc.plant.models import make_plant
from dmpc.plant.node import PlantNode
from dmpc.records.session import RunRecorder
from dmpc.run_spec import Prepared
from dmpc.runtime.central_loop import CentralLoop
from dmpc.steps import StepRecord


@dataclass
class InProcessRun:
    """The nodes of one in-process run (exposed for tests that inject faults)."""

    bus: MemoryBus
    plant: PlantNode
    agents: list[AgentNode]


def build_run(prepared: Prepared, on_step: Callable[[StepRecord], None], run_id: str = "local",
              bus_for: Callable[[MemoryBus, str], Bus] | None = None) -> InProcessRun:
    """Create the bus, the plant node and one agent node per subsystem.

    Parameters
    ----------
    bus_for : callable (bus, node name) -> Bus, optional
        Wraps the shared bus per node (fault injection); identity by default.
    """
    bus = MemoryBus()
    if bus_for is not None:
        view = bus_for
    elif prepared.faults.is_clean:
        view = lambda b, name: b  # noqa: E731
    else:
        view = lambda b, name: FaultyBus(b, name, prepared.faults)  # noqa: E731
    system, design = prepared.system, prepared.design
    plant_bus = view(bus, PLANT_PROCESS)
    coordinator = Coordinator(system, design, make_plant(prepared), prepared.protocol, run_id,
                              policy=terminal_policy(prepared.method, system, design), clock=plant_bus.now)
    plant = PlantNode(plant_bus, coordinator, prepared.digest, on_step, mode=prepared.mode,
                      dt=prepared.dt, deadline=prepared.deadline)
    agents = []
    for i, name in enumerate(prepared.names):
        controller = AgentController(system, design, i, coupling=prepared.coupling, method=prepared.method)
        agents.append(AgentNode(view(bus, name), controller, prepared.names, run_id, prepared.digest,
                                plan_wait=prepared.plan_wait, scenario=prepared.name))
    plant.announce()
    for agent in agents:
        agent.announce()
    return InProcessRun(bus=bus, plant=plant, agents=agents)


def simulate(prepared: Prepared, on_step: Callable[[StepRecord], None], run_id: str = "local",
             bus_for: Callable[[MemoryBus, str], Bus] | None = None, startup_timeout: float = 60.0) -> InProcessRun:
    """Run the scenario to the end in this process; ``on_step`` sees every step as it completes.

    ``startup_timeout`` is in simulated seconds: agents whose Ready never gets through (a dead
    link) fail the run instead of retrying forever.
    """
    run = build_run(prepared, on_step, run_id, bus_for)
    if not run.bus.run(until=lambda: run.plant.started or run.plant.finished, timeout=startup_timeout):
        missing = sorted(set(prepared.names) - run.plant.ready)
        run.plant.fail(f"agents {', '.join(missing)} not ready within {startup_timeout:g} s of simulated time")
        return run
    finished = run.bus.run(until=lambda: run.plant.finished)
    if not finished:
        run.plant.fail("the in-memory run stalled (no events left before the last step)")
    return run


def record_run(prepared: Prepared, recorder: RunRecorder) -> tuple[dict, str]:
    """Run the prepared method in this process into a RunRecorder and complete its records.

    Distributed methods run their nodes on the in-memory bus (:func:`simulate`); ``centralized``
    runs one QP per step. Returns the summary and the failure ("" if none).
    """
    if not method_spec(prepared.method).distributed:
        result = CentralLoop(prepared.system, prepared.design).run(prepared.protocol.steps, recorder.on_step,
                                                                   plant=make_plant(prepared))
        summary = recorder.complete(runtime="in-process (centralized, no agents)", failure=result.failure or None)
        return summary, result.failure
    run = simulate(prepared, recorder.on_step)
    summary = recorder.complete(runtime="in-process", failure=run.plant.failure or None, rejected=run.plant.rejected,
                                rejected_reasons=run.plant.rejects.reasons, duplicates=run.plant.coordinator.duplicates,
                                inputs_refused=run.plant.coordinator.inputs_refused,
                                agents={a.name: a.report() for a in run.agents})
    return summary, run.plant.failure
