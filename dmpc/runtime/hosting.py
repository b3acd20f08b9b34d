"""Agents grouped into host processes: ``dmpc run --agents-per-process K``.

With K = 1 (the default) every agent is a process of its own, named ``agent-<name>``. With K > 1
the agents, in scenario order, are split into ceil(M / K) groups of nearly equal size (none above
K), each served by one ``dmpc agent --id A --id B ...`` process named ``host-<i>``. Consecutive
subsystems go together, so in a chain most neighbours share a process and their plans never
leave it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from dmpc.bus import keys

HOST_PREFIX = "host-"


@dataclass(frozen=True)
class Host:
    """One agent process of a run.

    Attributes
    ----------
    role : str
        ``agent-<name>`` for a lone agent, ``host-<i>`` (1-based) for a group.
    agents : tuple of str
        The subsystems it serves, in scenario order.
    """

    role: str
    agents: tuple[str, ...]


def check_per_process(per_process: int) -> int:
    """``per_process`` if it is an integer >= 1; ValueError naming it otherwise."""
    if isinstance(per_process, bool) or not isinstance(per_process, int) or per_process < 1:
        raise ValueError(f"agents per process must be an integer >= 1, got {per_process!r}")
    return per_process


def group_agents(names: Sequence[str], per_process: int) -> list[Host]:
    """The agent processes of a run of ``names`` with at most ``per_process`` agents each.

    Parameters
    ----------
    names : sequence of str
        Subsystem names in scenario order (M of them).
    per_process : int
        K >= 1.

    Returns
    -------
    list of Host
        ceil(M / K) hosts whose sizes differ by at most one; together they hold every name once,
        in order.
    """
    check_per_process(per_process)
    names = list(names)
    if per_process == 1:
        return [Host(keys.agent_role(name), (name,)) for name in names]
    count = -(-len(names) // per_process)
    size, extra = divmod(len(names), count) if count else (0, 0)
    hosts, start = [], 0
    for i in range(count):
        end = start + size + (1 if i < extra else 0)
        hosts.append(Host(f"{HOST_PREFIX}{i + 1}", tuple(names[start:end])))
        start = end
    return hosts
