"""A TCP relay that delays traffic: a real link delay between two Zenoh endpoints.

The relay listens on one address and, for every connection it accepts, opens one to the
target. Each chunk read from either side is held for ``delay ± jitter`` milliseconds and
then written to the other side. Bytes keep their order: a chunk is never released before the
one read ahead of it, so jitter stretches the gaps between chunks but cannot reorder them
(TCP could not deliver reordered bytes anyway).

The relay runs an asyncio loop in a background thread, so the caller's thread stays free for
signals (Ctrl-C, SIGTERM) and tests can run it in-process::

    with Relay(("127.0.0.1", 7448), ("127.0.0.1", 7447), delay_ms=5) as relay:
        ...  # connect to relay.address instead of the target

The hold is measured on the monotonic clock and a chunk is never written early. It can be
late by the event loop's wake-up latency (about a millisecond on an idle machine).
"""
from __future__ import annotations

import asyncio
import random
import re
import socket
import threading
from dataclasses import dataclass

from dmpc.core.errors import DmpcError

CHUNK = 65536
QUEUE_CHUNKS = 1024  # per direction: at most 64 MiB held; a full queue stops reading (TCP back-pressure)

_ADDRESS = re.compile(r"^(?:tcp/)?(?P<host>\[[0-9A-Fa-f:.%]+\]|[A-Za-z0-9_.-]+):(?P<port>\d{1,5})$")


class RelayError(DmpcError, RuntimeError):
    """The relay cannot run: its listening address is taken or invalid."""


def parse_address(text: str, *, listen: bool = False) -> tuple[str, int]:
    """``HOST:PORT`` (or ``tcp/HOST:PORT``, ``[::1]:PORT``) as ``(host, port)``; ValueError otherwise.

    Parameters
    ----------
    text : str
        The address as typed.
    listen : bool
        Port 0 (any free port) is accepted only for listening.
    """
    match = _ADDRESS.match(text.strip())
    if match is None:
        raise ValueError(f"expected HOST:PORT such as 127.0.0.1:7447, got {text!r}")
    port = int(match["port"])
    if port > 65535 or (port == 0 and not listen):
        raise ValueError(f"port {port} in {text!r} is not usable here")
    return match["host"].strip("[]"), port


def _family(host: str) -> int:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _reason(exc: BaseException) -> str:
    """The short reason of a socket error, e.g. 'Address already in use'."""
    if isinstance(exc, OSError) and exc.strerror:
        # socket.create_server appends "(while attempting to bind on address ...)"
        return exc.strerror.split(" (while attempting")[0].removeprefix(f"[Errno {exc.errno}] ")
    return str(exc)


def format_address(address: tuple[str, int]) -> str:
    """``host:port`` of ``address`` (host, port), with brackets around an IPv6 host."""
    host, port = address
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


@dataclass
class RelayStats:
    """Counters of a relay, updated as it runs (read them from any thread).

    Attributes
    ----------
    connections : int
        Connections accepted.
    failed : int
        Accepted connections dropped because the target could not be reached.
    chunks, bytes : int
        Chunks and bytes written, both directions together.
    max_late_ms : float
        The most a chunk was written after its hold time (event-loop latency).
    """

    connections: int = 0
    failed: int = 0
    chunks: int = 0
    bytes: int = 0
    max_late_ms: float = 0.0


class Relay:
    """Forward TCP connections from ``listen`` to ``target``, holding every chunk for a delay.

    Parameters
    ----------
    listen : (str, int)
        Address to accept connections on; port 0 picks a free port (see ``address``).
    target : (str, int)
        Address every accepted connection is forwarded to.
    delay_ms : float
        Hold time of each chunk, in milliseconds, in each direction.
    jitter_ms : float
        Each chunk's hold is drawn uniformly from ``[delay - jitter, delay + jitter]`` (clipped
        at 0), then raised, if needed, so that it leaves no earlier than the chunk before it.
    seed : int or None
        Seed of the jitter. Each direction of each connection draws from its own generator,
        seeded by ``(seed, connection number, direction)``.
    """

    def __init__(self, listen: tuple[str, int], target: tuple[str, int], delay_ms: float,
                 jitter_ms: float = 0.0, seed: int | None = None) -> None:
        if delay_ms < 0 or jitter_ms < 0:
            raise ValueError("delay and jitter must be >= 0 ms")
        self.listen = listen
        self.target = target
        self.delay = delay_ms / 1000.0
        self.jitter = jitter_ms / 1000.0
        self.seed = seed
        self.stats = RelayStats()
        self._address: tuple[str, int] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stop: asyncio.Event | None = None
        self._tasks: set[asyncio.Task] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self.error: BaseException | None = None  # what ended the loop, if not stop()

    # ------------------------------------------------------------------ control (caller's thread)
    @property
    def address(self) -> tuple[str, int]:
        """The address actually listened on (the real port when ``listen`` asked for port 0)."""
        if self._address is None:
            raise RuntimeError("the relay is not started")
        return self._address

    @property
    def running(self) -> bool:
        """True from a successful ``start`` until ``stop`` (or an unexpected error, see ``error``)."""
        return self._thread is not None and self._thread.is_alive()

    def start(self, timeout: float = 5.0) -> None:
        """Listen and serve in a background thread; RelayError if the address cannot be bound within
        ``timeout`` seconds."""
        if self._thread is not None:
            raise RuntimeError("a relay starts only once")
        ready = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(target=self._run, args=(ready, failure), name="dmpc-relay", daemon=True)
        self._thread.start()
        if not ready.wait(timeout):
            raise RelayError(f"cannot listen on {format_address(self.listen)} (no answer within {timeout} s)")
        if failure:
            self._thread.join()
            raise RelayError(f"cannot listen on {format_address(self.listen)} ({_reason(failure[0])})") from None

    def stop(self, timeout: float = 1.0) -> None:
        """Close the listener and every connection (data still held is dropped), waiting at most
        ``timeout`` seconds for the thread; idempotent."""
        loop, thread, stop = self._loop, self._thread, self._stop
        if loop is not None and thread is not None and stop is not None and thread.is_alive():
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:  # the loop closed in between
                pass
            thread.join(timeout)

    def __enter__(self) -> "Relay":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ the loop (relay thread)
    def _run(self, ready: threading.Event, failure: list) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._serve(ready, failure))
        except BaseException as exc:  # noqa: BLE001 - reported to start(), or kept in ``error``
            if not ready.is_set():
                failure.append(exc)
                ready.set()
            else:
                self.error = exc
        finally:
            loop.close()

    async def _serve(self, ready: threading.Event, failure: list) -> None:
        self._stop = asyncio.Event()
        try:
            sock = socket.create_server(self.listen, family=_family(self.listen[0]))
            server = await asyncio.start_server(self._accept, sock=sock)
        except OSError as exc:
            failure.append(exc)
            ready.set()
            return
        bound = sock.getsockname()
        self._address = (bound[0], bound[1])
        ready.set()
        try:
            await self._stop.wait()
        finally:
            server.close()
            for writer in list(self._writers):
                writer.transport.abort()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)

    def _spawn(self, coro) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One connection: open the target, then relay both directions until both are closed."""
        self.stats.connections += 1
        number = self.stats.connections
        task = asyncio.current_task()
        assert task is not None  # asyncio runs each connection's handler as a task
        self._tasks.add(task)
        self._writers.add(writer)
        try:
            try:
                up_reader, up_writer = await asyncio.open_connection(*self.target)
            except OSError:
                self.stats.failed += 1
                return
            self._writers.add(up_writer)
            try:
                await self._relay(reader, writer, up_reader, up_writer, number)
            finally:
                up_writer.transport.abort()
                self._writers.discard(up_writer)
        except asyncio.CancelledError:
            pass  # the relay is stopping; asyncio's stream machinery reports a cancelled handler as an error
        finally:
            writer.transport.abort()
            self._writers.discard(writer)
            self._tasks.discard(task)

    async def _relay(self, reader, writer, up_reader, up_writer, number: int) -> None:
        """Four tasks: a reader and a delayed writer per direction; any failure ends them all."""
        to_target: asyncio.Queue = asyncio.Queue(QUEUE_CHUNKS)
        to_client: asyncio.Queue = asyncio.Queue(QUEUE_CHUNKS)
        tasks = [self._spawn(self._read(reader, to_target, self._rng(number, 0))),
                 self._spawn(self._send(to_target, up_writer)),
                 self._spawn(self._read(up_reader, to_client, self._rng(number, 1))),
                 self._spawn(self._send(to_client, writer))]
        pending = set(tasks)
        try:
            while pending:
                done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_EXCEPTION)
                if any(not t.cancelled() and t.exception() is not None for t in done):
                    break
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    def _rng(self, connection: int, direction: int) -> random.Random:
        return random.Random(None if self.seed is None else f"{self.seed}/{connection}/{direction}")

    def _hold(self, rng: random.Random) -> float:
        if self.jitter == 0:
            return self.delay
        return max(0.0, self.delay + rng.uniform(-self.jitter, self.jitter))

    async def _read(self, reader: asyncio.StreamReader, queue: asyncio.Queue, rng: random.Random) -> None:
        """Read chunks from one side and queue each with the time it may leave."""
        loop = asyncio.get_running_loop()
        last = 0.0
        while True:
            data = await reader.read(CHUNK)
            if not data:
                break
            last = max(loop.time() + self._hold(rng), last)  # never ahead of the chunk before it
            await queue.put((last, data))
        await queue.put((last, b""))  # end of stream, after the last chunk

    async def _send(self, queue: asyncio.Queue, writer: asyncio.StreamWriter) -> None:
        """Write each queued chunk to the other side once its hold is over."""
        loop = asyncio.get_running_loop()
        while True:
            due, data = await queue.get()
            while (wait := due - loop.time()) > 0:
                await asyncio.sleep(wait)
            if not data:
                if writer.can_write_eof() and not writer.transport.is_closing():
                    writer.write_eof()
                return
            self.stats.max_late_ms = max(self.stats.max_late_ms, (loop.time() - due) * 1000)
            writer.write(data)
            await writer.drain()
            self.stats.chunks += 1
            self.stats.bytes += len(data)
