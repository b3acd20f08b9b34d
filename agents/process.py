"""``dmpc agent``: one subsystem's controller as its own process on the Zenoh bus."""
from __future__ import annotations

import logging
from dataclasses import dataclass

from dmpc.agents.controller import AgentController
from dmpc.agents.node import AgentNode
from dmpc.bus.interface import Bus
from dmpc.runtime.setup import Prepared

log = logging.getLogger("dmpc.agent")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130


@dataclass(frozen=True)
class AgentOutcome:
    code: int
    message: str


def run_agent(prepared: Prepared, name: str, bus: Bus, run_id: str, startup_timeout: float) -> AgentOutcome:
    """Serve agent ``name`` until the plant stops the run, the plant is lost, or Ctrl-C.

    Parameters
    ----------
    prepared : Prepared
    name : str
        The subsystem name (``--id``).
    bus : Bus
        An open bus; closed by the caller.
    run_id : str
    startup_timeout : float
        Seconds to wait for the plant's first release before giving up.
    """
    index = prepared.names.index(name)
    controller = AgentController(prepared.system, prepared.design, index,
                                 coupling=prepared.coupling)
    node = AgentNode(bus, controller, prepared.names, run_id, prepared.digest, plan_wait=prepared.plan_wait)
    node.announce()
    started = bus.run(until=lambda: node.released or node.stopped or node.plant_lost, timeout=startup_timeout)
    if not started:
        missing = sorted({"plant"} | {f"agent-{n}" for n in node.neighbour_names} - node.peers_alive)
        return AgentOutcome(EXIT_FAILED, f"agent {name}: no release from the plant within {startup_timeout:g} s "
                                         f"(not seen alive: {', '.join(missing) or 'none'}; run id '{run_id}')")
    bus.run(until=lambda: node.stopped or node.plant_lost)
    if node.plant_lost and not node.stopped:
        return AgentOutcome(EXIT_FAILED, f"agent {name}: lost the plant after {node.solves} solves; exiting")
    if node.stop_reason.startswith("failed"):
        return AgentOutcome(EXIT_FAILED, f"agent {name}: the plant stopped the run ({node.stop_reason})")
    return AgentOutcome(EXIT_OK, f"agent {name}: {node.stop_reason} after {node.solves} solves")
