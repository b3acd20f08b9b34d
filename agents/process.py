"""``dmpc agent``: one subsystem's controller as its own process on the Zenoh bus."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

from dmpc.agents.controller import AgentController
from dmpc.agents.node import AgentNode
from dmpc.bus.interface import Bus
from dmpc.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK
from dmpc.runtime.setup import Prepared

log = logging.getLogger("dmpc.agent")

# After the plant's liveliness goes, wait this long for it to come back before exiting. A link
# that broke (or this process, hung past the lease and resumed) reconnects within it: at once,
# or at Zenoh's first connect retry one second later. A crashed plant never comes back: its
# liveliness goes at once (a hung one's after the lease), and the agents exit this long later.
PLANT_GRACE = 1.5


@dataclass(frozen=True)
class AgentOutcome:
    """How an agent process ended.

    Attributes
    ----------
    code : int
        The exit code.
    message : str
        One line for the terminal.
    report : dict
        :meth:`AgentNode.report`: messages dropped per sender and reason, duplicates, solves.
    """

    code: int
    message: str
    report: dict = field(default_factory=dict)


def run_agent(prepared: Prepared, name: str, bus: Bus, run_id: str, startup_timeout: float) -> AgentOutcome:
    """Serve agent ``name`` until the plant stops the run, the plant is lost for longer than
    ``PLANT_GRACE``, or Ctrl-C. A plant that comes back within the grace is rejoined.

    The outcome's message and report say how many invalid messages were dropped, per sender.

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
                                 coupling=prepared.coupling, method=prepared.method)
    node = AgentNode(bus, controller, prepared.names, run_id, prepared.digest, plan_wait=prepared.plan_wait,
                     scenario=prepared.name)
    node.announce()
    try:
        code, message = _serve(node, bus, name, run_id, startup_timeout)
    except KeyboardInterrupt:
        code, message = EXIT_INTERRUPTED, f"agent {name}: interrupted after {node.solves} solves"
    if node.rejects.total:
        message += f"; {node.rejects.counts_line()}"
    if node.duplicates:
        message += f"; {node.duplicates} duplicates ignored"
    return AgentOutcome(code, message, node.report())


def _serve(node: AgentNode, bus: Bus, name: str, run_id: str, startup_timeout: float) -> tuple[int, str]:
    started = bus.run(until=lambda: node.released or node.stopped or node.plant_lost, timeout=startup_timeout)
    if not started:
        missing = sorted({"plant"} | {f"agent-{n}" for n in node.neighbour_names} - node.peers_alive)
        return EXIT_FAILED, (f"agent {name}: no release from the plant within {startup_timeout:g} s "
                             f"(not seen alive: {', '.join(missing) or 'none'}; run id '{run_id}')")
    while not _run_until_plant_lost(node, bus):
        log.warning("agent %s: lost the plant; waiting %g s for it to come back", name, PLANT_GRACE)
        if not bus.run(until=lambda: node.stopped or not node.plant_lost, timeout=PLANT_GRACE):
            return EXIT_FAILED, f"agent {name}: lost the plant after {node.solves} solves; exiting"
    if node.design_refused:
        return EXIT_FAILED, (f"agent {name}: its design differs from the plant's: this agent uses design "
                             f"{node.design_digest} (scenario '{node.scenario}', horizon {node.controller.N}); "
                             f"the plant stopped the run ({node.stop_reason})")
    if node.stop_reason.startswith("failed"):
        return EXIT_FAILED, f"agent {name}: the plant stopped the run ({node.stop_reason})"
    return EXIT_OK, f"agent {name}: {node.stop_reason} after {node.solves} solves"


def _run_until_plant_lost(node: AgentNode, bus: Bus) -> bool:
    """Serve releases until the run stops (True) or the plant's liveliness goes (False)."""
    bus.run(until=lambda: node.stopped or node.plant_lost)
    return node.stopped
