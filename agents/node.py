"""Agent i on a bus: receives releases and neighbours' plans, solves, publishes its plan.

The same class runs in the in-process simulation (in-memory bus) and in an agent process
(Zenoh bus). Everything that arrives is decoded and checked (run id, sender against its key,
shapes, finiteness, step and round within the window below); anything invalid is dropped and
counted per sender, never raised out of a handler. A message seen twice is used once.
"""
from __future__ import annotations

import logging
import os
from collections import OrderedDict
from collections.abc import Callable
from typing import TypeVar

from dmpc.agents.controller import AgentController
from dmpc.agents.cooperative import CooperativeController
from dmpc.bus import keys
from dmpc.bus.codec import MAX_NAME, DecodeError, VersionMismatch, decode, encode
from dmpc.bus.interface import Bus, Timer
from dmpc.bus.messages import COORDINATOR, Kept, Message, PlanMessage, Ready, Release, Stop, design_claim
from dmpc.core.qp_status import SOLVED
from dmpc.core.trajectories import Plan
from dmpc.security.rejects import Rejections, out_of_range

log = logging.getLogger("dmpc.agent")
_Received = TypeVar("_Received", Release, PlanMessage, Stop)  # what an agent decodes from the bus
KEEP_PLANS = 8
# A release may skip ahead of the last one (releases lost on the way, a deadline passed) by at
# most this many steps or rounds; beyond it the message cannot come from this run's coordinator.
RELEASE_WINDOW = 1000


class AgentNode:
    """One agent's protocol logic.

    Parameters
    ----------
    bus : Bus
    controller : AgentController or CooperativeController
    names : list of str
        Subsystem names in index order.
    run_id : str
    design_digest : str
        Sent in ``Ready`` so the coordinator can check both sides use the same design.
    plan_wait : float or None
        How long to wait for a neighbour's referenced plan before using the newest older one;
        None waits as long as it takes (lockstep without losses).
    scenario : str
        The scenario's name, sent in ``Ready`` with the horizon so that the coordinator can say how
        a differing design differs.
    on_change : callable () -> None, optional
        Called on the bus's thread when ``released``, ``stopped`` or ``coordinator_lost`` changes
        (a process serving several agents waits for that).
    """

    def __init__(self, bus: Bus, controller: AgentController | CooperativeController, names: list[str], run_id: str,
                 design_digest: str, plan_wait: float | None = None, scenario: str = "",
                 on_change: Callable[[], None] | None = None) -> None:
        self.bus = bus
        self._on_change = on_change or _unchanged
        self.controller = controller
        self.names = names
        self.run_id = run_id
        self.design_digest = design_digest
        self.scenario = scenario[:MAX_NAME]
        self.plan_wait = plan_wait
        i = controller.index
        self.name = names[i]
        self.system = controller.system
        self.neighbour_names = {names[j]: j for j in controller.neighbours}
        self._watched = {keys.COORDINATOR_ROLE} | {keys.agent_role(n) for n in self.neighbour_names}
        self._known = frozenset(names)
        N = controller.N
        self._plan_shapes = {name: ((N + 1, self.system.subsystems[j].n), (N, self.system.subsystems[j].m))
                             for name, j in self.neighbour_names.items()}
        self.plans: dict[str, OrderedDict] = {name: OrderedDict() for name in self.neighbour_names}
        self.pending: Release | None = None
        self._wait_timer: Timer | None = None
        self._last_done: tuple[int, int] = (-1, -1)
        self.stopped = False
        self.stop_reason = ""
        self.coordinator_version: VersionMismatch | None = None  # set if the coordinator speaks another protocol
        self.rejects = Rejections(log, f"agent {self.name}", bus.now, [COORDINATOR, *self.neighbour_names])
        self.rejected: dict[str, int] = self.rejects.counts
        self.duplicates = 0
        self._latest: tuple[int, int] | None = None  # newest release accepted
        self.solves = 0
        self.keeps = 0
        self._previous: Release | None = None  # the release answered before (for the kept plans of its step)
        self.peers_alive: set[str] = set()
        self.coordinator_seen = False
        self.coordinator_lost = False
        self.rejoins = 0
        self._released = False
        self.released_at: float | None = None  # bus time of the first release
        self._first_k: int | None = None
        self._ready_timer: Timer | None = None
        self._repeat = 0.5
        bus.subscribe(keys.release(run_id), self._on_release, hot=True)
        for name in self.neighbour_names:
            bus.subscribe(keys.plan(run_id, name), self._on_plan, hot=True)
        bus.subscribe(keys.control(run_id), self._on_control)

    def announce(self, repeat: float = 0.5) -> None:
        """Hold a liveliness token and tell the coordinator this agent is ready.

        The token is declared after every subscriber (declarations travel in order, so whoever
        sees the token can reach the subscribers). ``Ready`` goes out once the coordinator and every
        neighbour are alive, and again every ``repeat`` seconds until the first release comes,
        in case the coordinator subscribed after the first one.
        """
        self.bus.watch_alive(keys.alive_prefix(self.run_id), self._on_alive)
        self.bus.declare_alive(keys.alive(self.run_id, keys.agent_role(self.name)))
        self._repeat = repeat

    def _on_alive(self, key: str, alive: bool) -> None:
        role = keys.last_chunk(key)
        if role not in self._watched:
            return  # only the coordinator and the neighbours matter (and the set stays bounded)
        if alive:
            self.peers_alive.add(role)
            if role == keys.COORDINATOR_ROLE:
                self.coordinator_seen = True
                if self.coordinator_lost and not self.stopped:
                    self._rejoin()
            self._maybe_ready()
        else:
            self.peers_alive.discard(role)
            if role == keys.COORDINATOR_ROLE and self.coordinator_seen and not self.stopped:
                self.coordinator_lost = True
                self._on_change()

    def _rejoin(self) -> None:
        """The coordinator is back after a loss (this process hung past the lease, or the link broke).

        The coordinator has declared this agent lost and releases nothing to it until it is ready
        again, so start over as at start-up: send ``Ready`` (repeated until a release comes) and
        treat the next release as the first (plans published meanwhile can never arrive).
        """
        log.warning("agent %s: the coordinator is back; rejoining", self.name)
        self.coordinator_lost = False
        self._released = False
        self._latest = None
        self.rejoins += 1
        self._on_change()

    def _maybe_ready(self) -> None:
        if self._released or self._ready_timer is not None:
            return
        needed = {keys.COORDINATOR_ROLE} | {keys.agent_role(n) for n in self.neighbour_names}
        if needed <= self.peers_alive:
            self._send_ready()

    def _send_ready(self) -> None:
        self._ready_timer = None
        if self._released or self.stopped:
            return
        msg = Ready(run=self.run_id, sender=self.name, design_digest=self.design_digest, pid=os.getpid(),
                    scenario=self.scenario, horizon=self.controller.N)
        self.bus.publish(keys.ready(self.run_id, self.name), encode(msg))
        self._ready_timer = self.bus.call_later(self._repeat, self._send_ready)

    # ------------------------------------------------------------------ receive
    def _reject(self, sender: str, why: str) -> None:
        self.rejects(sender, why)

    def _decode(self, key: str, payload: bytes, expected: type[_Received]) -> _Received | None:
        sender = keys.last_chunk(key) if expected is PlanMessage else COORDINATOR
        try:
            msg = _decode_shared(payload)
        except DecodeError as exc:
            if isinstance(exc, VersionMismatch) and sender == COORDINATOR:
                self.coordinator_version = exc  # its text names both versions
            self._reject(sender, str(exc))
            return None
        if not isinstance(msg, expected):
            self._reject(sender, f"unexpected {type(msg).__name__} on {key}")
            return None
        if msg.run != self.run_id:
            self._reject(sender, "wrong run id")
            return None
        return msg

    def _checked(self, check, msg, sender: str) -> bool:
        """Run ``check(msg)``; a problem (or a check that fails on odd input) drops the message."""
        try:
            problem = check(msg)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the agent
            problem = f"malformed: {type(exc).__name__}"
        if problem:
            self._reject(sender, problem)
            return False
        return True

    def _on_control(self, key: str, payload: bytes) -> None:
        msg = self._decode(key, payload, Stop)
        if msg is None or not self._checked(self._check_stop, msg, COORDINATOR) or self.stopped:
            return
        self.stopped = True
        self.stop_reason = msg.reason
        if self._ready_timer is not None:
            self._ready_timer.cancel()
            self._ready_timer = None
        self._on_change()

    def _check_stop(self, msg: Stop) -> str | None:
        if msg.sender != COORDINATOR:
            return "stop from another sender"
        if self._latest is not None and msg.k < self._latest[0]:
            return f"stale: stop at step {msg.k} after a release of step {self._latest[0]}"
        return None

    def _on_release(self, key: str, payload: bytes) -> None:
        msg = self._decode(key, payload, Release)
        if msg is None or self.name in msg.skipped or not self._checked(self._check_release, msg, COORDINATOR):
            return  # a round that skips this agent is not for it: the coordinator counts it as lost
        if (msg.k, msg.round) <= max(self._last_done, self._latest or self._last_done):
            self.duplicates += 1  # seen already, or older than one seen: a newer release supersedes it
            return
        self._latest = (msg.k, msg.round)
        if msg.kept:
            self._rebuild_kept(msg)
        self._previous = msg
        self._prune_plans(msg.k)
        if not self._released:
            self._released = True
            self._first_k = msg.k
            if self.released_at is None:
                self.released_at = self.bus.now()
            if self._ready_timer is not None:
                self._ready_timer.cancel()
                self._ready_timer = None
            self._on_change()
        self.pending = msg
        self._cancel_wait()
        self._try_solve()

    def _rebuild_kept(self, release: Release) -> None:
        """The plans of step k - 1 that the neighbours in ``release.kept`` kept, rebuilt from their
        plans that the previous release referred to, with its state and centres (nothing is sent
        for a kept plan). Without that release or that plan, the plan stays unknown: the solve
        then waits for it as for a lost one."""
        previous, k = self._previous, release.k - 1
        if previous is None or previous.k != k:
            return
        kept = release.kept_set
        for name, j in self.neighbour_names.items():
            if name not in kept:
                continue
            ref = previous.reference(j)
            plan = None if ref is None else self.plans[name].get(ref)
            if ref is not None and name in previous.provided:
                plan = Plan(ref[0], ref[1], *previous.provided[name])
            if plan is None:
                continue
            self.plans[name][(k, 0)] = self.controller.neighbour_kept(j, plan, previous)

    def _check_release(self, msg: Release) -> str | None:
        if msg.sender != COORDINATOR:
            return "release from another sender"
        if self._latest is not None:
            k, it = self._latest
            if msg.k > k + RELEASE_WINDOW or (msg.k == k and msg.round > it + RELEASE_WINDOW):
                return f"future: step {msg.k} round {msg.round} is too far ahead of step {k} round {it}"
        if msg.x.shape != (self.system.n,):
            return "release state has the wrong shape"
        if msg.sizes.shape != (self.system.M,):
            return "release sizes do not match the agents"
        for name, j in self.neighbour_names.items():
            ref_k, ref_it = msg.assumed[j]
            if ref_k >= 0 and (ref_k, ref_it) >= (msg.k, msg.round):
                return f"assumed plan of {name} is not older than the release"
        for name, (z, v) in msg.provided.items():
            if name not in self._known:
                return f"provided plan of unknown agent {name}"
            shapes = self._plan_shapes.get(name)
            if shapes is not None and (z.shape, v.shape) != shapes:
                return f"provided plan of {name} does not fit"
        return None

    def _on_plan(self, key: str, payload: bytes) -> None:
        msg = self._decode(key, payload, PlanMessage)
        name = keys.last_chunk(key)
        if msg is None or not self._checked(lambda m: self._check_plan(name, m), msg, name):
            return
        if msg.status not in SOLVED:
            return  # the coordinator falls back for it; nothing to assume from
        store = self.plans[name]
        if (msg.k, msg.round) in store:
            self.duplicates += 1  # the first copy stays
            return
        store[(msg.k, msg.round)] = Plan(msg.k, msg.round, msg.z, msg.v)
        while len(store) > KEEP_PLANS:
            store.popitem(last=False)
        if self.pending is not None:
            self._try_solve()

    def _check_plan(self, name: str, msg: PlanMessage) -> str | None:
        shapes = self._plan_shapes.get(name)
        if shapes is None or msg.sender != name:
            return "sender does not match its key"
        if (msg.z.shape, msg.v.shape) != shapes:
            return "plan has the wrong shape"
        if msg.status in SOLVED and out_of_range(msg.z, msg.v):
            return "out of range: plan values beyond the magnitude limit"
        if self._latest is not None:
            k = self._latest[0]
            if msg.k > k + 1:
                return f"future: plan of step {msg.k} while the last release is of step {k}"
            if msg.k < k - KEEP_PLANS:
                return f"stale: plan of step {msg.k} while the last release is of step {k}"
        return None

    def _prune_plans(self, k: int) -> None:
        """Forget plans stored before the first release that lie beyond the window of step ``k``
        (the newest release's).

        Old plans stay: the coordinator may keep referring to a lost neighbour's last plan.
        """
        for store in self.plans.values():
            for ref in [ref for ref in store if ref[0] > k + 1]:
                del store[ref]

    # ------------------------------------------------------------------ solve
    def _lookup(self, name: str, ref: tuple[int, int] | None, exact: bool) -> tuple[bool, Plan | None]:
        if ref is None:
            return True, None
        store = self.plans[name]
        if ref in store:
            return True, store[ref]
        if exact:
            return False, None
        older = [key for key in store if key <= ref]
        return True, (store[max(older)] if older else None)

    def _try_solve(self, exact: bool = True) -> None:
        release = self.pending
        if release is None or self.stopped:
            return
        plans: dict[int, Plan | None] = {}
        for name, j in self.neighbour_names.items():
            ref = release.reference(j)
            if ref is not None and name in release.provided:
                z, v = release.provided[name]
                plans[j] = Plan(ref[0], ref[1], z, v)
                continue
            # plans published before this agent (re)joined can never arrive: don't wait for them
            found, plan = self._lookup(name, ref, exact and (ref is None or ref[0] >= (self._first_k or 0)))
            if not found:
                self._arm_wait()
                self.bus.expect(keys.plan(self.run_id, name))
                return
            plans[j] = plan
        self.pending = None
        self._cancel_wait()
        self.bus.expect(None)
        msg = self.controller.answer(release, plans, self.run_id, clock=self.bus.now)
        self._last_done = (release.k, release.round)
        if isinstance(msg, Kept):
            self.keeps += 1
            self.bus.publish(keys.kept(self.run_id, self.name), encode(msg))
            return
        self.solves += 1
        self.bus.publish(keys.plan(self.run_id, self.name), encode(msg))

    def _arm_wait(self) -> None:
        if self.plan_wait is not None and self._wait_timer is None:
            self._wait_timer = self.bus.call_later(self.plan_wait, self._wait_expired)

    def _wait_expired(self) -> None:
        self._wait_timer = None
        self._try_solve(exact=False)

    def _cancel_wait(self) -> None:
        if self._wait_timer is not None:
            self._wait_timer.cancel()
            self._wait_timer = None

    @property
    def design_refused(self) -> bool:
        """True if the coordinator stopped the run naming this agent's design as different from its own."""
        return self.stopped and design_claim(self.name, self.design_digest) in self.stop_reason

    @property
    def released(self) -> bool:
        """True once the first release arrived (the run has started for this agent)."""
        return self._released

    def report(self) -> dict:
        """What this agent dropped and ignored, for the records (``summary.json`` ``agents``).

        Returns
        -------
        dict
            ``rejected`` (drops per sender), ``rejected_reasons`` (drops per reason),
            ``duplicates`` (copies ignored), ``solves``, ``keeps`` (plans kept by the event trigger).
        """
        return {"rejected": dict(self.rejects.counts), "rejected_reasons": dict(self.rejects.reasons),
                "duplicates": int(self.duplicates), "solves": int(self.solves), "keeps": int(self.keeps)}


def _unchanged() -> None:
    pass


class _LastDecoded:
    """The payload decoded last in this process and what it gave: a message or its DecodeError."""

    def __init__(self) -> None:
        self.payload: bytes | None = None
        self.result: Message | DecodeError | None = None


_last_decoded = _LastDecoded()


def _decode_shared(payload: bytes) -> Message:
    """``decode(payload)``, once per payload object: the agents of one process are handed the same
    bytes of a release or a plan (the bus fans them out), and decoded messages are read-only
    (their arrays are views on the payload), so they share the decoding. Each agent still makes
    its own checks and counts its own drops."""
    last = _last_decoded
    if last.payload is not payload:
        result: Message | DecodeError
        try:
            result = decode(payload)
        except DecodeError as exc:
            result = exc
        last.payload, last.result = payload, result
    if isinstance(last.result, DecodeError):
        raise last.result
    assert last.result is not None  # set with the payload
    return last.result
