"""The transport interface shared by the in-memory bus and the Zenoh bus.

Handlers and timers always run on the thread that calls ``run``: node code is single-threaded
whatever the transport. Payloads are bytes; encoding is the nodes' business (``bus.codec``).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

Handler = Callable[[str, bytes], None]
AliveHandler = Callable[[str, bool], None]
Reply = Callable[[bytes | None], None]
"""Ends one query: with a reply carrying the bytes given, or (None) without one."""
QueryHandler = Callable[[str, bytes, Reply], None]


class Timer(ABC):
    @abstractmethod
    def cancel(self) -> None:
        """Do not fire (no effect if it already fired)."""


class Broadcast(ABC):
    """A best-effort publisher on one key for observers outside the run (the live view): a
    message may be lost, and ``put`` never waits for a slow subscriber. It may be used from
    another thread than the one that runs the bus."""

    @abstractmethod
    def put(self, payload: bytes) -> None:
        """Send ``payload`` if the transport can take it now; raise if it cannot send at all."""

    @property
    @abstractmethod
    def matched(self) -> bool:
        """Some subscriber matches the key now (nothing needs to be sent while none does)."""

    @abstractmethod
    def close(self) -> None:
        """Stop publishing; idempotent, never raises."""


class Bus(ABC):
    """Publish/subscribe with liveliness and one clock."""

    @abstractmethod
    def publish(self, key: str, payload: bytes) -> None:
        """Send ``payload`` to every subscriber of ``key``."""

    @abstractmethod
    def subscribe(self, key: str, handler: Handler, hot: bool = False) -> None:
        """Call ``handler(key, payload)`` for each message on ``key`` (``prefix/*`` matches one chunk).

        ``hot`` marks the subscription the node waits on in its steady state (the releases for an
        agent, the plans for the plant): a transport may read it on the dispatch thread directly.
        Messages keep their order per key; across keys, a hot one may be handled before others
        that arrived just before it.
        """

    def serve(self, key: str, handler: QueryHandler) -> None:  # noqa: B027 - optional: most nodes answer no queries
        """Answer the queries on ``key`` (``prefix/*`` matches one chunk): ``handler(key, payload,
        reply)`` on the dispatch thread for each, whose ``reply`` must be called once, then or
        later, on that thread: ``reply(data)`` sends the one reply and ends the query, ``reply(None)``
        ends it without one. A transport without queries never calls the handler."""

    def expect(self, key: str | None) -> None:  # noqa: B027 - a hint with a default: most transports ignore it
        """A hint: the node's next needed message comes on hot key ``key`` (None: any). Transports
        that wait on one hot key at a time wait on it; others ignore the hint."""

    def broadcast(self, key: str, encoding: str) -> Broadcast | None:
        """A :class:`Broadcast` on ``key`` with payloads of ``encoding`` (a MIME type), or None
        for a transport that nothing outside the run can observe (the in-memory bus)."""
        return None

    @abstractmethod
    def declare_alive(self, key: str) -> None:
        """Hold a liveliness token on ``key`` until the bus is closed (or the process dies)."""

    @abstractmethod
    def watch_alive(self, pattern: str, handler: AliveHandler) -> None:
        """Call ``handler(key, alive)`` when a token matching ``pattern`` appears or disappears,
        including the tokens that exist already."""

    @abstractmethod
    def now(self) -> float:
        """Seconds on the bus's clock (simulated for the in-memory bus)."""

    @abstractmethod
    def call_later(self, delay: float, fn: Callable[[], None]) -> Timer:
        """Run ``fn`` on the dispatch thread after ``delay`` seconds of bus time."""

    @property
    def call_later_threadsafe(self) -> bool:
        """True if :meth:`call_later` may be called from any thread: a worker thread can hand its
        result to the dispatch thread. False for a bus whose time is simulated (the in-memory bus),
        where nothing may happen outside its events."""
        return False

    @abstractmethod
    def run(self, until: Callable[[], bool], timeout: float | None = None) -> bool:
        """Dispatch messages and timers until ``until()`` is true (returns True) or ``timeout``
        seconds of bus time pass (returns False)."""

    @abstractmethod
    def close(self) -> None:
        """Release every resource; idempotent."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def key_matches(pattern: str, key: str) -> bool:
    """Whether ``key`` matches ``pattern``: exactly, or ``a/b/*`` matching ``a/b/<one chunk>``."""
    if pattern.endswith("/*"):
        prefix = pattern[:-1]
        return key.startswith(prefix) and "/" not in key[len(prefix):] and len(key) > len(prefix)
    return pattern == key
