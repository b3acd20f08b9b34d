"""Helpers for the Zenoh bus tests: loopback configurations and child-process entry points.

The child functions live in an importable module (not the test file) because processes are
started with the ``spawn`` method, which imports the target by name.
"""
from __future__ import annotations

import contextlib
import multiprocessing
import statistics
import sys
import time

from dmpc.bus.session import free_tcp_port, open_session, session_config
from dmpc.bus.zenoh_bus import ZenohBus

DATA, DONE, PING, PONG, STOP = "t/data", "t/done", "t/ping", "t/pong", "t/stop"


def listen_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def listener(port: int, mode: str = "peer") -> ZenohBus:
    """A bus listening on ``port`` on loopback, multicast off."""
    return ZenohBus(session_config(mode=mode, listen=[listen_endpoint(port)]), open_timeout=10)


def connector(port: int, mode: str = "peer", timeout: float = 10.0) -> ZenohBus:
    """A bus connecting to ``port`` on loopback (retrying for ``timeout`` seconds)."""
    return ZenohBus(session_config(mode=mode, connect=[listen_endpoint(port)]), open_timeout=timeout)


@contextlib.contextmanager
def peer_pair():
    """Two connected peers ``(a, b)``; ``a`` listens, ``b`` connects. Both closed on exit."""
    port = free_tcp_port()
    a = listener(port)
    try:
        b = connector(port)
        try:
            yield a, b
        finally:
            b.close()
    finally:
        a.close()


def spawn_context():
    return multiprocessing.get_context("spawn")


def stop_process(proc, timeout: float = 5.0) -> None:
    """Join ``proc``; terminate (then kill) it if it does not exit in time."""
    proc.join(timeout)
    if proc.is_alive():
        proc.terminate()
        proc.join(2.0)
    if proc.is_alive():
        proc.kill()
        proc.join(2.0)


# -- child processes (spawned) ---------------------------------------------------------------


def child_publisher(port: int, count: int) -> None:
    """Connect to the parent, publish ``count`` numbered messages on DATA, wait for DONE."""
    done = []
    with connector(port, timeout=15) as bus:
        bus.subscribe(DONE, lambda key, payload: done.append(payload))
        if not bus.wait_for_subscribers(DATA, 15):
            sys.exit(2)
        for i in range(count):
            bus.publish(DATA, i.to_bytes(4, "little"))
        ok = bus.run(lambda: bool(done), timeout=20)
    sys.exit(0 if ok else 3)


def child_echo(port: int, mode: str = "peer") -> None:
    """Connect to the parent and answer every PING with a PONG carrying the same bytes."""
    stop = []
    with connector(port, mode=mode, timeout=15) as bus:
        bus.subscribe(PING, lambda key, payload: bus.publish(PONG, payload))
        bus.subscribe(STOP, lambda key, payload: stop.append(payload))
        ok = bus.run(lambda: bool(stop), timeout=60)
    sys.exit(0 if ok else 3)


def ping_pong(bus: ZenohBus, count: int, size: int = 64) -> list[float]:
    """Round trips in seconds of ``count`` sequential PING/PONG exchanges through an echo."""
    answers: list[bytes] = []
    bus.subscribe(PONG, lambda key, payload: answers.append(payload))
    if not bus.wait_for_subscribers(PING, 15):
        raise TimeoutError("the echo process never subscribed")
    # Warm up until the echo's PONG publisher sees our subscriber (declarations are async).
    deadline = time.monotonic() + 15
    while not answers:
        if time.monotonic() > deadline:
            raise TimeoutError("no PONG from the echo process")
        bus.publish(PING, b"warm-up")
        bus.run(lambda: bool(answers), timeout=0.2)
    bus.run(lambda: False, timeout=0.05)  # drain late warm-up answers
    rtts = []
    for i in range(count):
        answers.clear()
        payload = i.to_bytes(4, "little") + bytes(size - 4)
        start = bus.now()
        bus.publish(PING, payload)
        if not bus.run(lambda payload=payload: payload in answers, timeout=5):
            raise TimeoutError(f"PONG {i} lost")
        rtts.append(bus.now() - start)
    return rtts


def summary_us(rtts: list[float]) -> str:
    """``p50 / p90 / p99 / max`` in microseconds."""
    ordered = sorted(rtts)

    def pct(q: float) -> float:
        return ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1e6

    return (
        f"n={len(ordered)} p50={statistics.median(ordered) * 1e6:.0f} us "
        f"p90={pct(0.90):.0f} us p99={pct(0.99):.0f} us max={ordered[-1] * 1e6:.0f} us"
    )


@contextlib.contextmanager
def router(port: int):
    """A Python-hosted Zenoh router listening on ``port`` on loopback."""
    session = open_session(session_config(mode="router", listen=[listen_endpoint(port)]), 10)
    try:
        yield session
    finally:
        session.close()
