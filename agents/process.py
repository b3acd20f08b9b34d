"""``dmpc agent``: the controllers of one or more subsystems as one process on the Zenoh bus.

Several agents hosted by one process share its Zenoh session and its thread, and each behaves as
it does alone: its own subscriptions, liveliness token, ``Ready``, checks and report (see
``ZenohBus(shared=True)``). The process ends when every agent it serves has ended; a process that
dies is the loss of all its agents, which the coordinator sees as their liveliness going.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from dmpc.agents.controller import AgentController
from dmpc.agents.cooperative import CooperativeController
from dmpc.agents.node import AgentNode
from dmpc.bus import keys
from dmpc.bus.interface import Bus
from dmpc.bus.messages import COORDINATOR_GRACE
from dmpc.methods import method_spec
from dmpc.prepared import Prepared
from dmpc.records.agent_reports import FIRST_RELEASE
from dmpc.terminal.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK
from dmpc.terminal.signals import ignore_further_interrupts

log = logging.getLogger("dmpc.agent")


@dataclass(frozen=True)
class AgentOutcome:
    """How an agent ended.

    Attributes
    ----------
    code : int
        The exit code.
    message : str
        One line for the terminal.
    report : dict
        :meth:`AgentNode.report` (messages dropped per sender and reason, duplicates, solves) and
        ``FIRST_RELEASE``.
    """

    code: int
    message: str
    report: dict = field(default_factory=dict)


def agent_node(prepared: Prepared, name: str, bus: Bus, run_id: str,
               on_change: Callable[[], None] | None = None) -> AgentNode:
    """The controller of subsystem ``name`` of a prepared run, as a node on ``bus`` (not announced yet)
    in run ``run_id``; ``on_change`` is called when the node starts, stops or loses the coordinator.

    The one place that builds an agent from a prepared run: ``dmpc agent`` and ``dmpc simulate``
    (:mod:`dmpc.runtime.inprocess`) both do it here.
    """
    index = prepared.names.index(name)
    controller: AgentController | CooperativeController
    if method_spec(prepared.method).cooperative:
        controller = CooperativeController(prepared.system, prepared.design, index)
    else:
        controller = AgentController(prepared.system, prepared.design, index, coupling=prepared.coupling,
                                     method=prepared.method, trigger=prepared.trigger)
    return AgentNode(bus, controller, prepared.names, run_id, prepared.digest, plan_wait=prepared.plan_wait,
                     scenario=prepared.name, on_change=on_change)


def run_agent(prepared: Prepared, name: str, bus: Bus, run_id: str, startup_timeout: float) -> AgentOutcome:
    """Serve agent ``name`` alone: :func:`run_agents` with one name (``prepared``, ``bus``, ``run_id``
    and ``startup_timeout`` as there)."""
    return run_agents(prepared, [name], bus, run_id, startup_timeout)[0]


def run_agents(prepared: Prepared, names: Sequence[str], bus: Bus, run_id: str, startup_timeout: float,
               bus_for: Callable[[str], Bus] | None = None) -> list[AgentOutcome]:
    """Serve the agents ``names`` until the coordinator stops the run, the coordinator is lost for
    longer than ``COORDINATOR_GRACE``, or Ctrl-C. A coordinator that comes back within the grace is
    rejoined.

    Each outcome's message and report say how many invalid messages that agent dropped, per sender.

    Parameters
    ----------
    prepared : Prepared
    names : sequence of str
        The subsystem names (``--id``), each once.
    bus : Bus
        An open bus (``ZenohBus(shared=True)`` for more than one name); closed by the caller.
    run_id : str
    startup_timeout : float
        Seconds to wait for the coordinator's first release before giving up.
    bus_for : callable str -> Bus, optional
        The view of ``bus`` each agent uses (the fault injector's, with the agent as receiver);
        ``bus`` itself by default.

    Returns
    -------
    list of AgentOutcome
        In the order of ``names``.
    """
    changes = Changes()
    nodes = {name: agent_node(prepared, name, bus_for(name) if bus_for else bus, run_id, on_change=changes)
             for name in names}
    for node in nodes.values():
        node.announce()
    ends: dict[str, tuple[int, str]] = {}
    try:
        serve(nodes, bus, run_id, startup_timeout, changes, ends)
    except KeyboardInterrupt:
        ignore_further_interrupts()  # the reports below must be written whole
        for name, node in nodes.items():
            ends.setdefault(name, (EXIT_INTERRUPTED, f"agent {name}: interrupted after {node.solves} solves"))
    outcomes = []
    for name, node in nodes.items():
        code, message = ends[name]
        if node.rejects.total:
            message += f"; {node.rejects.counts_line()}"
        if node.duplicates:
            message += f"; {node.duplicates} duplicates ignored"
        outcomes.append(AgentOutcome(code, message, {**node.report(), FIRST_RELEASE: node.released_at}))
    return outcomes


def process_exit_code(outcomes: Sequence[AgentOutcome]) -> int:
    """The exit code of a process serving the agents of ``outcomes``: the worst of theirs (the highest)."""
    return max(o.code for o in outcomes)


class Changes:
    """The nodes' ``on_change``: set when one of them starts, stops or loses the coordinator."""

    __slots__ = ("pending",)

    def __init__(self) -> None:
        self.pending = False

    def __call__(self) -> None:
        self.pending = True


def serve(nodes: dict[str, AgentNode], bus: Bus, run_id: str, startup_timeout: float, changes: Changes,
          ends: dict[str, tuple[int, str]]) -> None:
    """Run the bus until every node has ended, filling ``ends`` with (exit code, message) per name.

    ``run_id`` names the run in the messages; a node that has no release within ``startup_timeout``
    seconds gives up. The nodes must have been made with ``on_change=changes``: the bus runs until a node changes
    or a deadline (start-up, a grace) comes, and only then are the nodes looked at, so the cost
    per message does not grow with the number of nodes.
    """
    start_by = bus.now() + startup_timeout
    grace_until: dict[str, float] = {}
    started: set[str] = set()  # released, stopped or lost the coordinator once: past the start-up timeout
    while len(ends) < len(nodes):
        now = bus.now()
        newly_lost = []
        for name, node in nodes.items():
            if name in ends:
                continue
            if node.released or node.stopped or node.coordinator_lost:
                started.add(name)
            if node.stopped:
                ends[name] = _stopped(name, node)
            elif node.coordinator_lost:
                if name not in grace_until:
                    grace_until[name] = now + COORDINATOR_GRACE
                    newly_lost.append(name)
                elif now >= grace_until[name]:
                    ends[name] = EXIT_FAILED, f"agent {name}: lost the coordinator after {node.solves} solves; exiting"
            else:
                grace_until.pop(name, None)
                if name not in started and now >= start_by:
                    ends[name] = EXIT_FAILED, _no_release(name, node, startup_timeout, run_id)
        if newly_lost:
            log.warning("agent%s %s: lost the coordinator; waiting %g s for it to come back",
                        "s" if len(newly_lost) > 1 else "", names_text(newly_lost), COORDINATOR_GRACE)
        waiting = [name for name in nodes if name not in ends]
        if not waiting:
            return
        deadlines = [grace_until[name] for name in waiting if name in grace_until]
        if any(name not in started for name in waiting):
            deadlines.append(start_by)
        changes.pending = False
        timeout = max(0.0, min(deadlines) - now) if deadlines else None
        if not bus.run(until=lambda: changes.pending, timeout=timeout) and timeout is None:
            for name in waiting:  # only an in-memory bus runs out of events
                ends[name] = EXIT_FAILED, f"agent {name}: the bus has nothing more to deliver"


def _stopped(name: str, node: AgentNode) -> tuple[int, str]:
    if node.design_refused:
        return EXIT_FAILED, (f"agent {name}: its design differs from the coordinator's: this agent uses design "
                             f"{node.design_digest} (scenario '{node.scenario}', horizon {node.controller.N}); "
                             f"the coordinator stopped the run ({node.stop_reason})")
    if node.stop_reason.startswith("failed"):
        return EXIT_FAILED, f"agent {name}: the coordinator stopped the run ({node.stop_reason})"
    return EXIT_OK, f"agent {name}: {node.stop_reason} after {node.solves} solves"


def _no_release(name: str, node: AgentNode, startup_timeout: float, run_id: str) -> str:
    missing = sorted({keys.COORDINATOR_ROLE} | {keys.agent_role(n) for n in node.neighbour_names} - node.peers_alive)
    version = f"; the coordinator speaks {node.coordinator_version}" if node.coordinator_version else ""
    return (f"agent {name}: no release from the coordinator within {startup_timeout:g} s "
            f"(not seen alive: {', '.join(missing) or 'none'}; run id '{run_id}'){version}")


def names_text(names: Sequence[str], shown: int = 6) -> str:
    """``names`` as ``1, 2, 3``, or the first and last few with the count when there are more than ``shown``."""
    names = list(names)
    if len(names) <= shown:
        return ", ".join(names)
    half = shown // 2
    return f"{', '.join(names[:half])}, ..., {', '.join(names[-half:])} ({len(names)} agents)"
