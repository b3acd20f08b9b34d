"""Seeded delay, jitter and loss per link, as a wrapper around any Bus.

Faults are applied on the receiving side: one publication reaches several subscribers, and each
(source -> receiver) link has its own delay and loss. The source of a message is read from its
key (``plan/<agent>`` and ``ready/<agent>`` come from that agent; releases and control from the
plant). Each link draws from its own random stream seeded by (seed, source, receiver), so a run
is reproducible and adding a link does not change the others' draws.
"""
from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from dmpc.bus.interface import AliveHandler, Broadcast, Bus, Handler, QueryHandler, Timer

# Fault links name the process that hosts the coordinator (and the simulated plant) "plant",
# as its log and process name do; agents are named by their subsystems.
PLANT_PROCESS = "plant"


@dataclass(frozen=True)
class LinkFault:
    """Delay ``delay_ms`` plus uniform jitter in [0, ``jitter_ms``], and drop with probability ``loss``."""

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0

    @property
    def is_clean(self) -> bool:
        return self.delay_ms == 0 and self.jitter_ms == 0 and self.loss == 0


@dataclass(frozen=True)
class FaultPlan:
    """Faults for every link: a default plus per-(source, receiver) overrides.

    Attributes
    ----------
    default : LinkFault
        The faults of every link not in ``links``.
    links : tuple of (source, receiver, LinkFault)
        The links with faults of their own.
    seed : int
        Seeds the draws of every link's faults."""

    default: LinkFault = LinkFault()
    links: tuple[tuple[str, str, LinkFault], ...] = ()
    seed: int = 0

    def link(self, source: str, receiver: str) -> LinkFault:
        """The faults of the link from ``source`` to ``receiver`` (the default unless overridden)."""
        for s, r, fault in self.links:
            if s == source and r == receiver:
                return fault
        return self.default

    @property
    def is_clean(self) -> bool:
        return self.default.is_clean and all(f.is_clean for _, _, f in self.links)

    def to_json(self) -> dict:
        """The plan as JSON-ready data, which :meth:`from_json` reads back."""
        return {"default": asdict(self.default), "links": [[s, r, asdict(f)] for s, r, f in self.links],
                "seed": self.seed}

    @classmethod
    def from_json(cls, data: dict) -> "FaultPlan":
        """The plan :meth:`to_json` gave, read from ``data`` (KeyError, TypeError or ValueError when malformed)."""
        return cls(default=LinkFault(**data["default"]),
                   links=tuple((s, r, LinkFault(**f)) for s, r, f in data["links"]), seed=int(data["seed"]))


def source_of(key: str) -> str:
    """The sender implied by a key expression of the protocol."""
    parts = key.split("/")
    if len(parts) >= 4 and parts[2] in ("plan", "ready"):
        return parts[3]
    return PLANT_PROCESS


class FaultyBus(Bus):
    """``inner`` as seen by node ``receiver`` through faulty links.

    Parameters
    ----------
    inner : Bus
    receiver : str
        The node this view belongs to (an agent name or ``plant``).
    plan : FaultPlan
    """

    def __init__(self, inner: Bus, receiver: str, plan: FaultPlan) -> None:
        self.inner = inner
        self.receiver = receiver
        self.plan = plan
        self._rngs: dict[str, np.random.Generator] = {}
        self.dropped = 0

    def _rng(self, source: str) -> np.random.Generator:
        rng = self._rngs.get(source)
        if rng is None:
            tag = zlib.crc32(f"{source}->{self.receiver}".encode())
            rng = self._rngs[source] = np.random.default_rng([self.plan.seed, tag])
        return rng

    def _wrap(self, handler: Handler) -> Handler:
        def deliver(key: str, payload: bytes) -> None:
            source = source_of(key)
            fault = self.plan.link(source, self.receiver)
            if fault.is_clean:
                handler(key, payload)
                return
            rng = self._rng(source)
            lost = rng.random() < fault.loss
            delay = (fault.delay_ms + fault.jitter_ms * rng.random()) / 1000.0
            if lost:
                self.dropped += 1
                return
            if delay <= 0:
                handler(key, payload)
                return
            self.inner.call_later(delay, lambda: handler(key, payload))

        return deliver

    def publish(self, key: str, payload: bytes) -> None:
        self.inner.publish(key, payload)

    def subscribe(self, key: str, handler: Handler, hot: bool = False) -> None:
        self.inner.subscribe(key, self._wrap(handler), hot)

    def expect(self, key: str | None) -> None:
        self.inner.expect(key)

    def serve(self, key: str, handler: QueryHandler) -> None:
        self.inner.serve(key, handler)  # the askers are outside the run (operators): no faults injected for them

    def broadcast(self, key: str, encoding: str) -> Broadcast | None:
        return self.inner.broadcast(key, encoding)  # observers are outside the run: no faults injected for them

    def declare_alive(self, key: str) -> None:
        self.inner.declare_alive(key)

    def watch_alive(self, pattern: str, handler: AliveHandler) -> None:
        self.inner.watch_alive(pattern, handler)

    def now(self) -> float:
        return self.inner.now()

    def call_later(self, delay: float, fn: Callable[[], None]) -> Timer:
        return self.inner.call_later(delay, fn)

    @property
    def call_later_threadsafe(self) -> bool:
        """Whether the inner bus's :meth:`call_later` may be called from any thread."""
        return self.inner.call_later_threadsafe

    def run(self, until: Callable[[], bool], timeout: float | None = None) -> bool:
        return self.inner.run(until, timeout)

    def close(self) -> None:
        self.inner.close()
