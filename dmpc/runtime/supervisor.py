"""Watching the processes of ``dmpc run``: progress, crashed agents restarted or lost, the end.

The protocol survives a lost agent (its fallback applies, ``docs/faults.md``) and takes a
restarted one back, so the launcher treats a crashed agent the same way:

- with restarts left (``--restart N``), it starts the agent again after a backoff of
  ``BACKOFF`` s, doubled for each further restart of that agent up to ``BACKOFF_MAX``; the new
  process rejoins as one started by hand would;
- otherwise the agent stays lost and the run goes on; ``--fail-fast`` stops the run instead.

A plant that fails ends the run. A plant that finishes (exit 0, or 3 for a failed verdict) ends
it too, after the agents have had ``AGENT_GRACE`` s to leave on their own.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from dmpc.terminal.exit_codes import EXIT_OK, EXIT_VERDICT

FINISHED = (EXIT_OK, EXIT_VERDICT)
"""Exit codes of a plant that ran to the end (the verdict is in summary.json)."""
BACKOFF = 0.5
BACKOFF_MAX = 8.0
AGENT_GRACE = 5.0
POLL = 0.05


@dataclass(frozen=True)
class RestartPolicy:
    """What to do when an agent process exits before the run ends.

    Attributes
    ----------
    restarts : int
        Restarts allowed per agent.
    fail_fast : bool
        Stop the whole run when an agent is lost for good.
    """

    restarts: int = 0
    fail_fast: bool = False


@dataclass
class Supervision:
    """What happened to the agent processes during the run: ``restarts`` per role, the roles ``lost``
    for good, and the exit codes of each role's crashes (``exits``)."""

    restarts: dict[str, int] = field(default_factory=dict)
    lost: list[str] = field(default_factory=list)
    exits: dict[str, list[int]] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"restarts": dict(self.restarts), "lost": list(self.lost), "crashes": dict(self.exits)}


@dataclass
class Ending:
    """How the supervised run ended: ``failed`` roles with their exit codes ({} if none), whether it was
    ``interrupted`` (Ctrl-C), and a ``message`` on it."""

    failed: dict[str, int]
    interrupted: bool = False
    message: str = ""


class Supervisor:
    """Runs the loop of one launch.

    Parameters
    ----------
    children : list of Child
        The plant first, then the agents, already started.
    spawn : callable Child -> None
        Starts a child (again).
    policy : RestartPolicy
    on_tick : callable () -> None, optional
        Called every poll (progress).
    clock, sleep : callable
        The time now and a pause (``time.monotonic`` and ``time.sleep``; tests pass their own).
    """

    def __init__(self, children, spawn, policy: RestartPolicy, on_tick=None, clock=time.monotonic,
                 sleep=time.sleep) -> None:
        self.children = children
        self.plant = children[0]
        self.agents = children[1:]
        self.spawn = spawn
        self.policy = policy
        self.on_tick = on_tick or (lambda: None)
        self.clock = clock
        self.sleep = sleep
        self.record = Supervision()
        self._due: dict[str, float] = {}  # role -> when to start it again
        self._gone: set[str] = set()  # lost for good

    def run(self) -> Ending:
        while True:
            self.on_tick()
            code = self.plant.poll()
            if code is not None:
                if code not in FINISHED:
                    return Ending({self.plant.role: code})
                self._wait_for_agents()
                return Ending({})
            ending = self._check_agents()
            if ending is not None:
                return ending
            self.sleep(POLL)

    def _check_agents(self) -> Ending | None:
        now = self.clock()
        for child in self.agents:
            name = child.role
            if name in self._gone:
                continue
            if name in self._due:
                if now >= self._due[name]:
                    del self._due[name]
                    self.spawn(child)
                continue
            code = child.poll()
            if code is None:
                continue
            if code == EXIT_OK:  # told to stop by the plant, which is finishing
                self._gone.add(name)
                continue
            self.record.exits.setdefault(name, []).append(code)
            used = self.record.restarts.get(name, 0)
            if used < self.policy.restarts:
                self.record.restarts[name] = used + 1
                self._due[name] = now + min(BACKOFF * 2 ** used, BACKOFF_MAX)
                continue
            self._gone.add(name)
            self.record.lost.append(name)
            if self.policy.fail_fast:
                return Ending({name: code}, message=f"{name} exited with code {code} (--fail-fast)")
        return None

    def _wait_for_agents(self) -> None:
        """After the plant finished: agents leave on their own within AGENT_GRACE s."""
        deadline = self.clock() + AGENT_GRACE
        while self.clock() < deadline:
            if all(c.poll() is not None for c in self.agents):
                return
            self.sleep(0.02)


def restart_note(record: Supervision) -> str:
    """One line on the restarts and lost agents of ``record`` ("" if none)."""
    parts = []
    if record.restarts:
        parts.append("restarted " + ", ".join(f"{name} x{n}" for name, n in sorted(record.restarts.items())))
    if record.lost:
        parts.append("lost " + ", ".join(sorted(record.lost)))
    return "; ".join(parts)
