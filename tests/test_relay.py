"""The TCP delay relay: bytes intact and in order, never earlier than the delay, clean shutdown."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time

import pytest

from dmpc.bus.relay import Relay, RelayError, format_address, parse_address
from tests.e2e_helpers import DMPC, ROOT


class Sink:
    """A TCP server that records what it receives (with arrival times) and can echo it back."""

    def __init__(self, echo: bool = False) -> None:
        self.echo = echo
        self.server = socket.create_server(("127.0.0.1", 0))
        self.address = self.server.getsockname()
        self.received = bytearray()
        self.arrivals: list[tuple[float, int]] = []  # (time, offset of the first byte of the recv)
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.server.accept()
        with conn:
            while True:
                data = conn.recv(65536)
                if not data:
                    break
                self.arrivals.append((time.monotonic(), len(self.received)))
                self.received += data
                if self.echo:
                    conn.sendall(data)
        self.done.set()

    def arrival_of(self, offset: int) -> float:
        """When the byte at ``offset`` arrived."""
        for t, start in reversed(self.arrivals):
            if start <= offset:
                return t
        raise AssertionError(f"byte {offset} never arrived")

    def close(self) -> None:
        self.server.close()


@pytest.fixture
def sink():
    s = Sink()
    yield s
    s.close()


def _connect(relay: Relay) -> socket.socket:
    sock = socket.create_connection(relay.address, timeout=10)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def test_parse_address():
    assert parse_address("127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert parse_address("tcp/plant.local:7447") == ("plant.local", 7447)
    assert parse_address("[::1]:7447") == ("::1", 7447)
    assert parse_address("0.0.0.0:0", listen=True) == ("0.0.0.0", 0)
    assert format_address(("::1", 7)) == "[::1]:7"
    for bad in ("7447", "host", "host:", "a b:1", "h:70000"):
        with pytest.raises(ValueError, match="HOST:PORT|not usable"):
            parse_address(bad)
    with pytest.raises(ValueError, match="port 0"):
        parse_address("127.0.0.1:0")


def test_chunks_arrive_intact_in_order_and_not_before_the_delay(sink):
    delay = 20.0
    payload, sends = bytearray(), []  # sends: (time, offset of the chunk's first byte)
    with Relay(("127.0.0.1", 0), sink.address, delay_ms=delay) as relay:
        with _connect(relay) as sock:
            for i in range(40):
                chunk = os.urandom(1 + (i * 997) % 5000)
                sends.append((time.monotonic(), len(payload)))
                payload += chunk
                sock.sendall(chunk)
                time.sleep(0.003)
        assert sink.done.wait(10), "end of stream not relayed"
        late = relay.stats.max_late_ms
    assert bytes(sink.received) == bytes(payload)
    holds = [(sink.arrival_of(offset) - t) * 1000 for t, offset in sends]
    assert min(holds) >= delay, f"a chunk arrived after {min(holds):.2f} ms < {delay} ms"
    excess = sorted(h - delay for h in holds)
    print(f"relay hold {delay} ms: excess median {excess[len(excess) // 2]:.2f} ms, max {excess[-1]:.2f} ms; "
          f"relay's own lateness at most {late:.2f} ms")
    assert excess[len(excess) // 2] < 15  # generous: the machine is shared


def test_round_trip_holds_both_directions():
    delay = 10.0
    echo = Sink(echo=True)
    try:
        with Relay(("127.0.0.1", 0), echo.address, delay_ms=delay) as relay, _connect(relay) as sock:
            rtts = []
            for i in range(20):
                message = f"ping {i:03d}".encode()
                t0 = time.monotonic()
                sock.sendall(message)
                got = b""
                while len(got) < len(message):
                    got += sock.recv(64)
                rtts.append((time.monotonic() - t0) * 1000)
                assert got == message
    finally:
        echo.close()
    assert min(rtts) >= 2 * delay
    print(f"round trip through a {delay} ms relay: min {min(rtts):.2f} ms, median {sorted(rtts)[10]:.2f} ms")


def test_jitter_keeps_byte_order_and_bounds(sink):
    delay, jitter = 10.0, 8.0
    payload, sends = bytearray(), []
    with Relay(("127.0.0.1", 0), sink.address, delay_ms=delay, jitter_ms=jitter, seed=3) as relay:
        with _connect(relay) as sock:
            for i in range(60):
                chunk = i.to_bytes(2, "big") * 50
                sends.append((time.monotonic(), len(payload)))
                payload += chunk
                sock.sendall(chunk)
                time.sleep(0.002)
        assert sink.done.wait(10)
    assert bytes(sink.received) == bytes(payload)
    holds = [(sink.arrival_of(offset) - t) * 1000 for t, offset in sends]
    assert min(holds) >= delay - jitter
    assert max(holds) - min(holds) > 2  # the jitter is there


def test_seeded_jitter_is_reproducible():
    a = Relay(("127.0.0.1", 0), ("127.0.0.1", 1), delay_ms=5, jitter_ms=2, seed=7)
    b = Relay(("127.0.0.1", 0), ("127.0.0.1", 1), delay_ms=5, jitter_ms=2, seed=7)
    ra, rb = a._rng(1, 0), b._rng(1, 0)
    draws = [a._hold(ra) for _ in range(50)]
    assert draws == [b._hold(rb) for _ in range(50)]
    assert all(0.003 <= d <= 0.007 for d in draws)
    assert draws != [a._hold(a._rng(1, 1)) for _ in range(50)]  # each direction its own stream


def test_large_transfer_both_ways_and_end_of_stream():
    echo = Sink(echo=True)
    data = os.urandom(8 * 1024 * 1024)
    received = bytearray()
    try:
        with Relay(("127.0.0.1", 0), echo.address, delay_ms=2) as relay, _connect(relay) as sock:
            def read_all():
                while chunk := sock.recv(1 << 16):
                    received.extend(chunk)

            reader = threading.Thread(target=read_all, daemon=True)
            reader.start()
            sock.sendall(data)
            sock.shutdown(socket.SHUT_WR)  # the echo server closes once it sees the end
            reader.join(30)
            assert not reader.is_alive(), "end of stream did not come back through the relay"
            assert relay.stats.connections == 1 and relay.stats.bytes == 2 * len(data)
    finally:
        echo.close()
    assert bytes(received) == data


def test_port_in_use_is_a_clear_error():
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        relay = Relay(("127.0.0.1", port), ("127.0.0.1", 1), delay_ms=1)
        with pytest.raises(RelayError, match=rf"cannot listen on 127.0.0.1:{port} \(.*in use\)"):
            relay.start()


def test_unreachable_target_closes_the_client():
    with socket.create_server(("127.0.0.1", 0)) as s:
        dead = s.getsockname()  # closed when the block ends: nothing listens there afterwards
    with Relay(("127.0.0.1", 0), dead, delay_ms=1) as relay, _connect(relay) as sock:
        sock.settimeout(5)
        try:
            assert sock.recv(10) == b""
        except ConnectionResetError:
            pass
        assert relay.stats.failed == 1


def test_stop_drops_connections_within_a_second(sink):
    relay = Relay(("127.0.0.1", 0), sink.address, delay_ms=5000)
    relay.start()
    sock = _connect(relay)
    try:
        sock.sendall(b"held for 5 s")
        time.sleep(0.1)
        t0 = time.monotonic()
        relay.stop()
        assert time.monotonic() - t0 < 1.0
        sock.settimeout(2)
        try:
            assert sock.recv(10) == b""
        except ConnectionResetError:
            pass
        assert sink.received == b""  # held data is dropped, not flushed early
    finally:
        sock.close()


# ---------------------------------------------------------------------------- the command
def _start_cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen(DMPC + ["relay", *args], cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_cli_relays_and_stops_on_signal_within_a_second(sig):
    echo = Sink(echo=True)
    proc = _start_cli("--listen", "127.0.0.1:0", "--to", format_address(echo.address), "--delay", "5",
                      "--jitter", "1", "--seed", "1")
    try:
        banner = proc.stdout.readline()
        assert banner.startswith("relay 127.0.0.1:") and "delay 5 ± 1 ms" in banner
        port = int(banner.split()[1].rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(b"hello")
            assert sock.recv(5) == b"hello"
            t0 = time.monotonic()
            proc.send_signal(sig)
            proc.wait(timeout=5)
            assert time.monotonic() - t0 < 1.0
        out, err = proc.communicate()
        assert proc.returncode == 0, err
        assert "relay stopped: 1 connections" in out and "Traceback" not in err
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        echo.close()


@pytest.mark.parametrize("args, code, text", [
    (["--listen", "nowhere", "--to", "127.0.0.1:7447", "--delay", "1"], 2, "--listen: expected HOST:PORT"),
    (["--listen", "127.0.0.1:0", "--to", "127.0.0.1:0", "--delay", "1"], 2, "--to: port 0"),
    (["--listen", "127.0.0.1:0", "--to", "127.0.0.1:7447", "--delay", "-1"], 2, "--delay"),
])
def test_cli_bad_input_exits_2(args, code, text):
    res = subprocess.run(DMPC + ["relay", *args], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == code
    assert text in res.stderr and "Traceback" not in res.stderr


def test_cli_cannot_listen_exits_1():
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        res = subprocess.run(DMPC + ["relay", "--listen", f"127.0.0.1:{port}", "--to", "127.0.0.1:7447",
                                     "--delay", "1"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 1
    assert res.stderr.startswith(f"error: relay: cannot listen on 127.0.0.1:{port}")
    assert "in use" in res.stderr and "Traceback" not in res.stderr
