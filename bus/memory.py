"""An in-process bus: a deterministic discrete-event scheduler on a simulated clock.

Deliveries and timers are events ordered by (time, sequence number). Publishing schedules a
delivery for every matching subscriber at the current time; nothing is shared by reference,
the payload bytes are what travels.
"""
from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from functools import partial

from dmpc.bus.interface import AliveHandler, Bus, Handler, QueryHandler, Timer, key_matches


class _MemoryTimer(Timer):
    def __init__(self) -> None:
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class MemoryBus(Bus):
    """Single-threaded in-memory bus shared by every node of an in-process run.

    Parameters
    ----------
    max_events : int
        Safety stop for ``run``: a protocol bug that loops forever raises RuntimeError.
    """

    def __init__(self, max_events: int = 50_000_000) -> None:
        self._time = 0.0
        self._seq = itertools.count()
        self._events: list = []
        self._subs: list[tuple[str, Handler]] = []
        self._servers: list[tuple[str, QueryHandler]] = []
        self._alive: set[str] = set()
        self._watchers: list[tuple[str, AliveHandler]] = []
        self._max_events = max_events
        self._closed = False

    def _schedule(self, at: float, fn: Callable[[], None], timer: _MemoryTimer | None = None) -> None:
        heapq.heappush(self._events, (at, next(self._seq), fn, timer))

    def publish(self, key: str, payload: bytes) -> None:
        data = bytes(payload)
        for pattern, handler in list(self._subs):
            if key_matches(pattern, key):
                self._schedule(self._time, partial(handler, key, data))

    def subscribe(self, key: str, handler: Handler, hot: bool = False) -> None:
        self._subs.append((key, handler))

    def serve(self, key: str, handler: QueryHandler) -> None:
        self._servers.append((key, handler))

    def ask(self, key: str, payload: bytes, on_reply: Callable[[bytes | None], None]) -> None:
        """Query ``key`` with ``payload``: each server of the key gets it as an event, and its reply
        (bytes, or None: ended without one) reaches ``on_reply`` as another."""
        data = bytes(payload)
        for pattern, handler in list(self._servers):
            if key_matches(pattern, key):
                def reply(answer: bytes | None) -> None:
                    self._schedule(self._time, partial(on_reply, None if answer is None else bytes(answer)))

                self._schedule(self._time, partial(handler, key, data, reply))

    def declare_alive(self, key: str) -> None:
        self._alive.add(key)
        self._notify(key, True)

    def drop_alive(self, key: str) -> None:
        """Withdraw the token on ``key`` (what a crashed process's session does)."""
        if key in self._alive:
            self._alive.discard(key)
            self._notify(key, False)

    def _notify(self, key: str, alive: bool) -> None:
        for pattern, handler in self._watchers:
            if key_matches(pattern, key):
                self._schedule(self._time, partial(handler, key, alive))

    def watch_alive(self, pattern: str, handler: AliveHandler) -> None:
        self._watchers.append((pattern, handler))
        for key in sorted(self._alive):
            if key_matches(pattern, key):
                self._schedule(self._time, partial(handler, key, True))

    def now(self) -> float:
        return self._time

    def call_later(self, delay: float, fn: Callable[[], None]) -> Timer:
        timer = _MemoryTimer()
        self._schedule(self._time + max(0.0, delay), fn, timer)
        return timer

    def run(self, until: Callable[[], bool], timeout: float | None = None) -> bool:
        end = None if timeout is None else self._time + timeout
        handled = 0
        while not until():
            if not self._events or (end is not None and self._events[0][0] > end):
                if end is not None:
                    self._time = max(self._time, end)
                return False
            at, _, fn, timer = heapq.heappop(self._events)
            self._time = max(self._time, at)
            if timer is not None and timer.cancelled:
                continue
            fn()
            handled += 1
            if handled > self._max_events:
                raise RuntimeError("in-memory bus: event limit reached (protocol loop?)")
        return True

    def close(self) -> None:
        self._closed = True
        self._events.clear()
        self._subs.clear()
        self._servers.clear()
