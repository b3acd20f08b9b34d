"""The Zenoh implementation of :class:`~dmpc.bus.interface.Bus`.

Handlers, liveliness events and timers all run on the thread that calls ``run``, so node code
stays single-threaded exactly as with the in-memory bus. Messages get there two ways:

- A **hot** subscription (see :meth:`ZenohBus.subscribe`) is a channel inside Zenoh that ``run``
  reads itself: a message goes from Zenoh's network thread straight to the ``run`` thread, and no
  Python code runs on Zenoh's threads for it. When idle, ``run`` waits on one hot channel: the one
  named by :meth:`ZenohBus.expect` (the message the node needs next), else the first one
  subscribed. The other hot channels are read whenever ``run`` wakes.
- Every other subscription and liveliness watch has a callback on Zenoh's thread that copies the
  key and payload onto one thread-safe queue. While ``run`` waits on a hot channel, such a
  callback (and a timer coming due, or every ``POLL`` seconds so that Ctrl-C is seen) wakes it
  with a message put on that channel's key inside this session only, carrying a random token that
  nothing else can send.

Messages keep their order per key; across keys, queued ones are handled first when ``run`` wakes,
then the hot channels other than the first, then the first.

Several handlers may subscribe to one key (or watch one liveliness pattern): the key has one Zenoh
subscriber, and each message reaches every handler in the order they subscribed.

Several nodes on one bus
------------------------
A bus opened with ``shared=True`` serves several nodes of one process (``dmpc agent --id A --id
B``), which behave as they do alone:

- a message published to a key that a node of this bus subscribes to is handed to its handlers
  here (through the queue, bytes as sent), and Zenoh carries it only to other processes;
- only the first hot key (the release, which every agent subscribes to) is read by ``run``
  itself; later hot subscriptions go through the queue. ``run`` can wait on one channel only, and
  a message on any other key must wake it at once, whichever node needs it;
- ``expect`` is ignored for the same reason.

Errors
------
A handler (or timer) that raises propagates out of ``run`` on the calling thread; the event is
consumed and the bus stays usable, so the caller may log and call ``run`` again. Nothing ever
raises into a Zenoh thread: failures there are counted in ``callback_errors`` and ``dropped``.
"""
from __future__ import annotations

import atexit
import heapq
import itertools
import logging
import os
import queue
import threading
import time
import weakref
from collections.abc import Callable

import zenoh

from dmpc.bus.interface import AliveHandler, Broadcast, Bus, Handler, QueryHandler, Reply, Timer, key_matches
from dmpc.bus.session import BusError, open_session, opens_abandoned, session_config

log = logging.getLogger(__name__)

ENCODING = "application/msgpack"
POLL = 0.1  # longest wait in run(): bounds the delay before Ctrl-C is seen
HOT_CAPACITY = 8192
"""Messages a hot channel holds for ``run``; beyond it the oldest are dropped (Zenoh's threads
never wait for the node)."""


class _Handlers(list):
    """Every handler of one subscription, called in the order they subscribed."""

    def __call__(self, key: str, value) -> None:
        for handler in self:
            handler(key, value)


class _Hot:
    """One hot key: its Zenoh subscriber (a ring channel), handlers and session-local waker."""

    __slots__ = ("key", "subscriber", "handlers", "waker")

    def __init__(self, key: str, subscriber, waker) -> None:
        self.key = key
        self.subscriber = subscriber
        self.handlers = _Handlers()
        self.waker = waker


class _Watch:
    """One watched liveliness pattern: the tokens alive as dispatched so far, and its handlers.

    A handler added after the first is primed on the ``run`` thread: it is told the tokens alive
    at that moment and then gets every later event, as a Zenoh subscriber with history would.
    """

    __slots__ = ("alive", "handlers")

    def __init__(self) -> None:
        self.alive: set[str] = set()
        self.handlers: list[list] = []  # [handler, primed]

    def add(self, handler: AliveHandler, primed: bool) -> list:
        slot = [handler, primed]
        self.handlers.append(slot)
        return slot

    def prime(self, slot: list) -> None:
        slot[1] = True
        for key in sorted(self.alive):
            slot[0](key, True)

    def __call__(self, key: str, alive: bool) -> None:
        if alive:
            self.alive.add(key)
        else:
            self.alive.discard(key)
        for handler, primed in self.handlers:
            if primed:
                handler(key, alive)
# Closing a session can wait for a link to a peer that is hung (stopped, but its kernel still
# accepts TCP connections); after this long the session is left to the process's exit.
CLOSE_TIMEOUT = 1.0

_open_buses: weakref.WeakSet[ZenohBus] = weakref.WeakSet()
# Sessions whose close did not finish: their closing thread must not outlive a normal interpreter
# exit (it would be torn down inside Zenoh's native code and abort the process), so the process
# should end with os._exit once its records are written.
_left_open: list[zenoh.Session] = []


def sessions_left_open() -> bool:
    """True if a session in this process did not close within CLOSE_TIMEOUT, or was left
    opening by an interrupted start-up."""
    return bool(_left_open) or opens_abandoned()


@atexit.register
def _close_leftovers() -> None:
    # Safety net: close any bus the caller forgot, so sessions end before interpreter teardown.
    for bus in list(_open_buses):
        bus.close()


class _ZenohTimer(Timer):
    __slots__ = ("fn", "cancelled")

    def __init__(self, fn: Callable[[], None]) -> None:
        self.fn = fn
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class _ZenohBroadcast(Broadcast):
    """A Zenoh publisher that drops what it cannot send at once, at low priority."""

    def __init__(self, publisher: zenoh.Publisher) -> None:
        self._publisher = publisher
        self._closed = False

    def put(self, payload: bytes) -> None:
        self._publisher.put(payload)

    @property
    def matched(self) -> bool:
        try:
            return _matching(self._publisher)
        except Exception:  # noqa: BLE001 - a closing session matches nothing
            return False

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._publisher.undeclare()
        except Exception:  # noqa: BLE001 - best effort on the way out
            pass


class ZenohBus(Bus):
    """Publish/subscribe, liveliness and timers over one Zenoh session.

    Parameters
    ----------
    source : zenoh.Config or zenoh.Session
        A configuration (opened with :func:`~dmpc.bus.session.open_session`) or an open
        session.
    open_timeout : float
        Seconds to reach the connect endpoints before failing with BusError.
    close_session : bool
        Close the session in :meth:`close` (default); False leaves a session passed in open.
    max_queue : int
        Messages waiting for ``run`` beyond this are dropped (counted in ``dropped``) rather
        than blocking Zenoh's threads.
    max_payload : int
        Larger payloads are dropped on arrival (counted in ``dropped``) and never queued: no
        message of the protocol comes near it, and a flood of big ones must not fill memory.
    shared : bool
        Several nodes of this process use the bus (see "Several nodes on one bus" above).

    Attributes
    ----------
    dropped : int
        Samples lost on the receiving side (queue full, or an error while copying one).
    callback_errors : int
        Exceptions caught on Zenoh's callback threads.
    """

    def __init__(
        self,
        source: zenoh.Config | zenoh.Session,
        *,
        open_timeout: float = 10.0,
        close_session: bool = True,
        max_queue: int = 1_000_000,
        max_payload: int = 1 << 20,
        shared: bool = False,
    ) -> None:
        if isinstance(source, zenoh.Config):
            self._session = open_session(source, open_timeout)
        elif isinstance(source, zenoh.Session):
            self._session = source
        else:
            raise TypeError(f"expected zenoh.Config or zenoh.Session, got {type(source).__name__}")
        self._close_session = close_session
        self._max_queue = max_queue
        self._max_payload = max_payload
        self._shared = shared
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._timers: list = []
        self._seq = itertools.count()
        self._lock = threading.Lock()  # publisher cache, timer heap, declarations, close
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._declared: list = []  # subscribers and tokens, undeclared in reverse on close
        self._closed = False
        self.dropped = 0
        self.callback_errors = 0
        self._hot: dict[str, _Hot] = {}  # by key, in the order subscribed
        self._subscribed: dict[str, _Handlers] = {}  # every key's handlers, hot or not
        self._queued: dict[str, _Handlers] = {}  # keys whose messages come through the queue
        self._wildcards: list[tuple[str, _Handlers]] = []  # for delivery inside a shared bus
        self._watches: dict[str, _Watch] = {}
        self._first: _Hot | None = None
        self._others: list[_Hot] = []
        self._expected: _Hot | None = None
        self._token = os.urandom(16)
        self._wait = threading.Condition(threading.Lock())  # guards the five fields below
        self._blocked: _Hot | None = None  # the hot channel run() is waiting on
        self._woken = False  # a wake-up message is on its way
        self._wake_at = 0.0  # when the alarm thread wakes run() at the latest
        self._alarm_at = 0.0  # when the alarm thread looks next (it is told only of earlier times)
        self._alarm: threading.Thread | None = None
        _open_buses.add(self)

    @classmethod
    def open(cls, *, timeout: float = 10.0, **options) -> ZenohBus:
        """Open a bus from :func:`~dmpc.bus.session.session_config` keyword arguments, waiting at most
        ``timeout`` seconds for the session."""
        return cls(session_config(**options), open_timeout=timeout)

    @property
    def session(self) -> zenoh.Session:
        """The underlying session (for readiness checks and diagnostics)."""
        return self._session

    # -- sending -------------------------------------------------------------------------

    def _publisher(self, key: str) -> zenoh.Publisher:
        publisher = self._publishers.get(key)
        if publisher is None:
            with self._lock:
                self._check_open()
                publisher = self._publishers.get(key)
                if publisher is None:
                    publisher = self._session.declare_publisher(
                        _key_expr(key),
                        encoding=ENCODING,
                        congestion_control=zenoh.CongestionControl.BLOCK,  # default is DROP
                        reliability=zenoh.Reliability.RELIABLE,
                        priority=zenoh.Priority.REAL_TIME,
                        # A shared bus publishes for many nodes in a row: batched by Zenoh's own
                        # thread, a put costs about 2 us instead of 30-40 us written on this
                        # thread, for the same latency (measured on loopback).
                        express=not self._shared,
                        # a shared bus hands its own nodes their messages itself (publish)
                        allowed_destination=zenoh.Locality.REMOTE if self._shared else zenoh.Locality.ANY,
                    )
                    self._publishers[key] = publisher
        return publisher

    def publish(self, key: str, payload: bytes) -> None:
        """Send ``payload`` to every subscriber of ``key`` (BusError once closed)."""
        self._check_open()
        data = bytes(payload)
        if self._shared:
            self._deliver_here(key, data)
        try:
            self._publisher(key).put(data)
        except zenoh.ZError as exc:
            raise BusError(f"publish on {key!r} failed: {exc}") from exc

    def broadcast(self, key: str, encoding: str) -> Broadcast:
        """A publisher for observers on ``key``, with payloads of ``encoding`` (a MIME type): congestion
        control DROP, best-effort reliability, low priority."""
        with self._lock:
            self._check_open()
            return _ZenohBroadcast(self._session.declare_publisher(
                _key_expr(key), encoding=encoding, congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.BEST_EFFORT, priority=zenoh.Priority.DATA_LOW, express=False))

    def _deliver_here(self, key: str, data: bytes) -> None:
        """Queue ``data`` for this bus's own subscribers of ``key`` (a shared bus)."""
        handlers = self._subscribed.get(key)
        if handlers is not None:
            self._enqueue(handlers, key, data)
        for pattern, more in self._wildcards:
            if key_matches(pattern, key):
                self._enqueue(more, key, data)

    def wait_for_subscribers(self, key: str, timeout: float) -> bool:
        """Wait until at least one subscriber matches ``key``; False after ``timeout`` seconds.

        Declarations spread asynchronously, so a message published right after a remote
        subscriber is declared may be missed. Messages arriving meanwhile stay queued.
        """
        publisher = self._publisher(key)
        deadline = time.monotonic() + timeout
        while not _matching(publisher):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.002)
        return True

    # -- receiving (Zenoh threads) ---------------------------------------------------------

    def _enqueue(self, handler: Callable, key: str, value) -> None:
        if self._queue.qsize() >= self._max_queue:
            self.dropped += 1
            return
        self._queue.put((handler, key, value))
        if self._first is not None:
            with self._wait:
                self._wake_locked()

    def _wake_locked(self) -> None:
        """Wake a run() waiting on a hot channel (call with ``_wait`` held)."""
        if self._blocked is not None and not self._woken:
            self._woken = True
            self._blocked.waker.put(self._token)

    def _on_sample(self, handler: Handler) -> zenoh.handlers.Callback:
        def callback(sample: zenoh.Sample) -> None:
            try:
                if len(sample.payload) > self._max_payload:
                    self.dropped += 1
                    return
                self._enqueue(handler, str(sample.key_expr), sample.payload.to_bytes())
            except BaseException:  # noqa: BLE001 - must not escape into Zenoh's thread
                self.callback_errors += 1
                self.dropped += 1

        return _direct(callback)

    def _on_alive(self, handler: AliveHandler) -> zenoh.handlers.Callback:
        def callback(sample: zenoh.Sample) -> None:
            try:
                alive = sample.kind == zenoh.SampleKind.PUT
                self._enqueue(handler, str(sample.key_expr), alive)
            except BaseException:  # noqa: BLE001
                self.callback_errors += 1
                self.dropped += 1

        return _direct(callback)

    def _declare(self, make: Callable[[], object]) -> None:
        with self._lock:
            self._check_open()
            self._declared.append(make())

    def subscribe(self, key: str, handler: Handler, hot: bool = False) -> None:
        """Call ``handler(key, payload)`` on the ``run`` thread for each message on ``key``.

        ``hot``: ``run`` reads this key's messages from Zenoh itself, without a hand-over
        between threads (on a shared bus, only for the first hot key). More handlers on the same
        key share its subscriber.
        """
        expr = _key_expr(key)
        if hot and self._shared and (key in self._queued or (self._first is not None and key not in self._hot)):
            hot = False  # a shared bus waits on one hot key only (see the module docstring)
        if hot:
            entry = self._hot.get(key)
            if entry is None:
                entry = self._declare_hot(key, expr)
            handlers = entry.handlers
        else:
            queued = self._queued.get(key)
            if queued is None:
                queued = self._queued[key] = _Handlers()
                self._declare(lambda: self._session.declare_subscriber(expr, self._on_sample(queued)))
            handlers = queued
        handlers.append(handler)
        if key not in self._subscribed:
            self._subscribed[key] = handlers
            if "*" in key:
                self._wildcards.append((key, handlers))

    def serve(self, key: str, handler: QueryHandler) -> None:
        """Answer the queries on ``key``: ``handler(key, payload, reply)`` on the ``run`` thread for
        each (:meth:`Bus.serve <dmpc.bus.interface.Bus.serve>`). A query whose ``reply`` is never
        called ends when it is forgotten; one dropped on arrival (too large, queue full) ends at once
        without a reply."""
        expr = _key_expr(key)

        def dispatch(key: str, value: tuple[bytes, zenoh.Query]) -> None:
            data, query = value
            handler(key, data, _replier(query))

        def callback(query: zenoh.Query) -> None:
            try:
                payload = query.payload
                if payload is not None and len(payload) > self._max_payload:
                    self.dropped += 1
                    query.drop()
                    return
                self._enqueue(dispatch, str(query.key_expr), (b"" if payload is None else payload.to_bytes(), query))
            except BaseException:  # noqa: BLE001 - must not escape into Zenoh's thread
                self.callback_errors += 1
                self.dropped += 1

        self._declare(lambda: self._session.declare_queryable(
            expr, zenoh.handlers.Callback(callback, indirect=False)))  # it only enqueues: see _direct

    def query(self, key: str, payload: bytes, timeout: float) -> list[bytes] | None:
        """Ask the queryables of ``key`` with ``payload`` and wait until the query ends, at most
        ``timeout`` seconds in all (waiting for a queryable to match included).

        Returns
        -------
        list of bytes or None
            The payloads of the replies once the query ended: none when every queryable that got
            it ended it without a reply, or when it was dropped on its way (an access control
            denies it without a word). None when no queryable matched ``key`` within ``timeout``.
        """
        deadline = time.monotonic() + timeout
        with self._lock:
            self._check_open()
            querier = self._session.declare_querier(_key_expr(key))
        try:
            while not querier.matching_status.matching:  # type: ignore[attr-defined]  # see _matching
                if time.monotonic() >= deadline:
                    return None
                time.sleep(0.002)
            replies = self._session.get(_key_expr(key), payload=bytes(payload), encoding=ENCODING,
                                        timeout=max(deadline - time.monotonic(), 0.001))
            return [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]
        except zenoh.ZError as exc:
            raise BusError(f"query on {key!r} failed: {exc}") from exc
        finally:
            try:
                querier.undeclare()
            except Exception:  # noqa: BLE001 - best effort: the session may be closing
                pass

    def _declare_hot(self, key: str, expr: zenoh.KeyExpr) -> _Hot:
        with self._lock:
            self._check_open()
            subscriber = self._session.declare_subscriber(expr, zenoh.handlers.RingChannel(HOT_CAPACITY))
            waker = self._session.declare_publisher(_key_expr(_wake_key(key)), express=True,
                                                    allowed_destination=zenoh.Locality.SESSION_LOCAL)
            entry = self._hot[key] = _Hot(key, subscriber, waker)
        if self._first is None:
            self._first = entry
            self._alarm = threading.Thread(target=self._alarm_loop, name="dmpc-bus-alarm", daemon=True)
            self._alarm.start()
        else:
            self._others.append(entry)
        return entry

    def expect(self, key: str | None) -> None:
        """Wait on hot key ``key`` when idle (None: the first hot key): the next message the node needs.

        A hint: messages on other keys are still handled, but a hot one may wait until ``run``
        wakes for another reason (at most ``POLL`` seconds). A shared bus ignores it.
        """
        if not self._shared:
            self._expected = self._hot.get(key) if key is not None else None

    def _alarm_loop(self) -> None:
        """Wake a run() waiting on the hot channel when its next timer or POLL comes due.

        It looks at least every POLL seconds; run() tells it only of wake times earlier than
        its next look, so that a wait that ends with a message costs it nothing.
        """
        with self._wait:
            while not self._closed:
                now = time.monotonic()
                waiting = self._blocked is not None and not self._woken
                if waiting and self._wake_at <= now:
                    try:
                        self._wake_locked()
                    except Exception:  # noqa: BLE001 - the session is closing
                        return
                    continue
                self._alarm_at = self._wake_at if waiting else now + POLL
                self._wait.wait(self._alarm_at - now)

    def declare_alive(self, key: str) -> None:
        """Hold a liveliness token on ``key`` until :meth:`close` (or the process dies)."""
        expr = _key_expr(key)
        self._declare(lambda: self._session.liveliness().declare_token(expr))

    def watch_alive(self, pattern: str, handler: AliveHandler) -> None:
        """Call ``handler(key, alive)`` on the ``run`` thread as tokens matching ``pattern``
        appear or disappear; tokens that exist already are reported as alive.

        Handlers of one pattern share its Zenoh subscriber; a later one is told the tokens
        alive when ``run`` reaches it, then every change.
        """
        expr = _key_expr(pattern)
        existing = self._watches.get(pattern)
        if existing is not None:
            slot = existing.add(handler, primed=False)
            self._enqueue(lambda _key, _value: existing.prime(slot), pattern, None)
            return
        watch = self._watches[pattern] = _Watch()
        watch.add(handler, primed=True)  # Zenoh's history brings it the tokens alive now
        self._declare(
            lambda: self._session.liveliness().declare_subscriber(
                expr, self._on_alive(watch), history=True
            )
        )

    # -- time and dispatch -----------------------------------------------------------------

    def now(self) -> float:
        """``time.monotonic()``: on Linux one clock for every process of a host."""
        return time.monotonic()

    @property
    def call_later_threadsafe(self) -> bool:
        """True: :meth:`call_later` may be called from any thread."""
        return True

    def call_later(self, delay: float, fn: Callable[[], None]) -> Timer:
        """Run ``fn`` on the ``run`` thread ``delay`` seconds from now (thread-safe)."""
        timer = _ZenohTimer(fn)
        due = time.monotonic() + max(0.0, delay)
        with self._lock:
            heapq.heappush(self._timers, (due, next(self._seq), timer))
        self._queue.put(None)  # wake a run() waiting on the queue so it sees the new deadline
        if self._first is not None:
            with self._wait:
                if self._blocked is not None and due < self._wake_at:
                    self._wake_at = due
                    if due < self._alarm_at:
                        self._wait.notify_all()
        return timer

    def _due_timer(self, now: float) -> tuple[_ZenohTimer | None, float | None]:
        """Pop the next due timer, or return the time of the next one."""
        if not self._timers:  # read without the lock: a timer added meanwhile wakes run() again
            return None, None
        with self._lock:
            while self._timers and self._timers[0][2].cancelled:
                heapq.heappop(self._timers)
            if not self._timers:
                return None, None
            if self._timers[0][0] <= now:
                return heapq.heappop(self._timers)[2], None
            return None, self._timers[0][0]

    def run(self, until: Callable[[], bool], timeout: float | None = None) -> bool:
        """Dispatch messages, liveliness events and timers on the calling thread.

        Returns True as soon as ``until()`` holds (checked before every event), False when
        ``timeout`` seconds pass first. Exceptions from handlers and timers propagate.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while not until():
            now = time.monotonic()
            timer, next_at = self._due_timer(now)
            if timer is not None:
                timer.fn()
                continue
            if deadline is not None and now >= deadline:
                return False
            wake_at = now + POLL
            for limit in (next_at, deadline):
                if limit is not None:
                    wake_at = min(wake_at, limit)
            item = self._next_item(wake_at)
            if item is not None:
                handler, key, value = item
                handler(key, value)
        return True

    def _next_item(self, wake_at: float):
        """The next event to handle, waiting until ``wake_at`` at most; None if there is none yet."""
        if self._first is None:
            try:
                return self._queue.get(timeout=max(wake_at - time.monotonic(), 0.0))
            except queue.Empty:
                return None
        if not self._queue.empty():
            try:
                return self._queue.get_nowait()
            except queue.Empty:
                pass
        for entry in self._others:
            sample = entry.subscriber.try_recv()
            if sample is not None:
                return self._hot_item(entry, sample)
        entry = self._first
        sample = entry.subscriber.try_recv()
        if sample is None:
            entry = self._expected or self._first
            with self._wait:
                if not self._queue.empty():
                    return None
                self._blocked, self._woken, self._wake_at = entry, False, wake_at
                if wake_at < self._alarm_at:
                    self._wait.notify_all()
            try:
                sample = entry.subscriber.recv()
            finally:
                with self._wait:
                    self._blocked = None
        return self._hot_item(entry, sample)

    def _hot_item(self, entry: _Hot, sample: zenoh.Sample):
        payload = sample.payload
        if len(payload) > self._max_payload:
            self.dropped += 1
            return None
        data = payload.to_bytes()
        if data == self._token:
            return None  # a wake-up
        handlers = entry.handlers
        if len(handlers) == 1:
            return handlers[0], str(sample.key_expr), data
        return handlers, str(sample.key_expr), data

    # -- shutdown --------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise BusError("the Zenoh bus is closed")

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare everything and close the session; idempotent, never raises."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            hot = [e for entry in self._hot.values() for e in (entry.waker, entry.subscriber)]
            entities = list(self._publishers.values()) + hot + self._declared[::-1]
            self._publishers.clear()
            self._declared.clear()
            self._timers.clear()
        with self._wait:
            self._wait.notify_all()  # the alarm thread sees _closed and ends
        for entity in entities:
            try:
                entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - best effort on the way out
                log.debug("undeclare failed: %s", exc)
        if self._close_session:
            closer = threading.Thread(target=_close_session, args=(self._session,), name="zenoh-close", daemon=True)
            closer.start()
            closer.join(CLOSE_TIMEOUT)
            if closer.is_alive():
                _left_open.append(self._session)
                log.info("the Zenoh session did not close within %g s (a peer is not answering); leaving it", CLOSE_TIMEOUT)
        _open_buses.discard(self)


def _close_session(session: zenoh.Session) -> None:
    try:
        session.close()
    except Exception as exc:  # noqa: BLE001 - best effort on the way out
        log.warning("closing the Zenoh session failed: %s", exc)


def _direct(fn: Callable[[zenoh.Sample], None]) -> zenoh.handlers.Callback:
    # A plain Python callable is run on an extra non-daemon Python thread ("indirect"), which
    # the interpreter joins at exit before atexit hooks run: a bus left open then hangs the
    # process. Our callbacks only enqueue, so they can run on Zenoh's own thread.
    return zenoh.handlers.Callback(fn, indirect=False)


def _replier(query: zenoh.Query) -> Reply:
    """The ``reply`` of one query: one reply on the query's key (or none), then the query's end."""

    def reply(payload: bytes | None) -> None:
        try:
            if payload is not None:
                query.reply(query.key_expr, payload, encoding=ENCODING)
        except zenoh.ZError as exc:
            log.debug("a reply could not be sent (the asker left, or the session is closing): %s", exc)
        finally:
            query.drop()

    return reply


def _matching(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches the publisher's key."""
    # zenoh's stub types the property as bool; it is a MatchingStatus, which says so in .matching
    return bool(publisher.matching_status.matching)  # type: ignore[attr-defined]


def _wake_key(key: str) -> str:
    """A key that the hot subscription ``key`` matches: its wildcard chunks replaced by ``_``."""
    return "/".join("_" if "*" in chunk else chunk for chunk in key.split("/"))


def _key_expr(key: str) -> zenoh.KeyExpr:
    try:
        return zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise ValueError(f"invalid key expression {key!r}: {exc}") from exc
