"""End-to-end tests of the Zenoh bus on loopback (multicast off, a free port per test)."""
from __future__ import annotations

import json
import threading
import time

import pytest

from dmpc.bus.session import (
    BusError,
    TlsFiles,
    check_endpoint,
    free_tcp_port,
    session_config,
)
from dmpc.bus.zenoh_bus import POLL, ZenohBus
from tests import helpers_zenoh as hz

pytestmark = pytest.mark.e2e


def collect(bus: ZenohBus, key: str) -> list:
    got: list = []
    bus.subscribe(key, lambda k, payload: got.append((k, payload)))
    return got


# -- configuration ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad", ["127.0.0.1:7447", "tcp/127.0.0.1", "tcp/host:99999", "foo/127.0.0.1:1", "tcp//:1", ""]
)
def test_bad_endpoint_is_named(bad):
    with pytest.raises(ValueError, match="endpoint"):
        session_config(connect=[bad])
    with pytest.raises(ValueError) as info:
        check_endpoint(bad)
    assert repr(bad) in str(info.value)


def test_connect_to_port_zero_refused():
    with pytest.raises(ValueError, match="tcp/127.0.0.1:0"):
        session_config(connect=["tcp/127.0.0.1:0"])


def test_peer_default_listen_follows_connect_endpoints():
    def listen_of(config):
        return json.loads(config.get_json("listen/endpoints"))

    assert listen_of(session_config(connect=["tcp/127.0.0.1:7447"])) == ["tcp/127.0.0.1:0"]
    assert listen_of(session_config(connect=["tcp/localhost:7447"])) == ["tcp/127.0.0.1:0"]
    assert listen_of(session_config(connect=["tcp/10.1.2.3:7447"])) == ["tcp/0.0.0.0:0"]
    assert listen_of(session_config(connect=["tcp/127.0.0.1:7447"], multicast=True)) == [
        "tcp/0.0.0.0:0"
    ]
    config = session_config(mode="client", connect=["tcp/127.0.0.1:7447"], lease_ms=1500)
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("transport/link/tx/lease")) == 1500
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False


def test_tls_keys_are_set(tmp_path):
    for name in ("ca.pem", "cert.pem", "key.pem"):
        (tmp_path / name).write_text("-")
    tls = TlsFiles(tmp_path / "ca.pem", tmp_path / "cert.pem", tmp_path / "key.pem")
    config = session_config(listen=["tls/127.0.0.1:0"], tls=tls)
    section = json.loads(config.get_json("transport/link/tls"))
    assert section["root_ca_certificate"] == str(tmp_path / "ca.pem")
    assert section["listen_certificate"] == section["connect_certificate"] == str(tmp_path / "cert.pem")
    assert section["listen_private_key"] == section["connect_private_key"] == str(tmp_path / "key.pem")
    assert section["enable_mtls"] is True
    with pytest.raises(ValueError, match="missing.pem"):
        session_config(tls=TlsFiles(tmp_path / "missing.pem", tls.cert, tls.key))


@pytest.mark.parametrize("mode", ["peer", "client"])
def test_unreachable_endpoint_fails_in_time(mode):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    start = time.monotonic()
    with pytest.raises(BusError, match=endpoint):
        ZenohBus(session_config(mode=mode, connect=[endpoint]), open_timeout=1.0)
    assert time.monotonic() - start < 3.0


def test_busy_listen_port_fails_with_bus_error():
    port = free_tcp_port()
    with hz.listener(port):
        with pytest.raises(BusError, match=f"127.0.0.1:{port}"):
            hz.listener(port)


# -- messages --------------------------------------------------------------------------------


def test_messages_both_ways_in_order():
    with hz.peer_pair() as (a, b):
        at_a, at_b = collect(a, "t/to_a"), collect(b, "t/to_b")
        assert a.wait_for_subscribers("t/to_b", 5) and b.wait_for_subscribers("t/to_a", 5)
        for i in range(20):
            a.publish("t/to_b", bytes([i]))
            b.publish("t/to_a", bytes([100 + i]))
        assert b.run(lambda: len(at_b) == 20, timeout=5)
        assert a.run(lambda: len(at_a) == 20, timeout=5)
        assert at_b == [("t/to_b", bytes([i])) for i in range(20)]
        assert at_a == [("t/to_a", bytes([100 + i])) for i in range(20)]


def test_prefix_subscription_matches_one_chunk():
    with hz.peer_pair() as (a, b):
        got = collect(b, "t/plan/*")
        assert a.wait_for_subscribers("t/plan/1", 5)
        a.publish("t/plan/1", b"one")
        a.publish("t/plan/1/deeper", b"no")
        a.publish("t/other/1", b"no")
        a.publish("t/plan/2", b"two")
        assert b.run(lambda: len(got) == 2, timeout=5)
        b.run(lambda: False, timeout=0.1)
        assert got == [("t/plan/1", b"one"), ("t/plan/2", b"two")]


def test_burst_of_1000_messages_all_arrive():
    with hz.peer_pair() as (a, b):
        got = collect(b, "t/burst")
        assert a.wait_for_subscribers("t/burst", 5)
        payloads = [i.to_bytes(4, "little") + bytes(1000) for i in range(1000)]
        for payload in payloads:
            a.publish("t/burst", payload)
        assert b.run(lambda: len(got) == 1000, timeout=10), f"{len(got)} of 1000"
        assert [p for _, p in got] == payloads
        assert b.dropped == 0 and b.callback_errors == 0


def test_handlers_run_on_the_run_thread():
    with hz.peer_pair() as (a, b):
        threads = []
        b.subscribe("t/x", lambda k, p: threads.append(threading.get_ident()))
        b.watch_alive("t/alive/*", lambda k, alive: threads.append(threading.get_ident()))
        b.call_later(0.0, lambda: threads.append(threading.get_ident()))
        a.declare_alive("t/alive/a")
        assert a.wait_for_subscribers("t/x", 5)
        a.publish("t/x", b"1")
        assert b.run(lambda: len(threads) == 3, timeout=5)
        assert set(threads) == {threading.get_ident()}


def test_handler_exception_propagates_and_bus_keeps_working():
    with hz.peer_pair() as (a, b):
        got = []

        def handler(key, payload):
            if payload == b"bad":
                raise ValueError("bad payload")
            got.append(payload)

        b.subscribe("t/x", handler)
        assert a.wait_for_subscribers("t/x", 5)
        for payload in (b"bad", b"ok1", b"ok2"):
            a.publish("t/x", payload)
        with pytest.raises(ValueError, match="bad payload"):
            b.run(lambda: False, timeout=5)
        assert b.run(lambda: len(got) == 2, timeout=5)
        assert got == [b"ok1", b"ok2"] and b.callback_errors == 0


# -- liveliness ------------------------------------------------------------------------------


def test_liveliness_appears_and_disappears_on_close():
    port = free_tcp_port()
    with hz.listener(port) as watcher:
        other = hz.connector(port)
        try:
            other.declare_alive("t/alive/early")
            events = []
            watcher.watch_alive("t/alive/*", lambda k, alive: events.append((k, alive)))
            assert watcher.run(lambda: ("t/alive/early", True) in events, timeout=5)
            other.declare_alive("t/alive/late")
            assert watcher.run(lambda: ("t/alive/late", True) in events, timeout=5)
        finally:
            other.close()
        gone = {("t/alive/early", False), ("t/alive/late", False)}
        assert watcher.run(lambda: gone <= set(events), timeout=5)


# -- timers and run --------------------------------------------------------------------------


def test_timers_fire_in_order_and_cancel():
    bus = ZenohBus(session_config(listen=["tcp/127.0.0.1:0"]))
    try:
        fired = []
        bus.call_later(0.06, lambda: fired.append("c"))
        bus.call_later(0.02, lambda: fired.append("a"))
        bus.call_later(0.04, lambda: fired.append("b"))
        bus.call_later(0.03, lambda: fired.append("cancelled")).cancel()
        start = bus.now()
        assert bus.run(lambda: len(fired) == 3, timeout=2)
        assert fired == ["a", "b", "c"]
        assert bus.now() - start >= 0.06
    finally:
        bus.close()


def test_run_timeout_and_until():
    bus = ZenohBus(session_config(listen=["tcp/127.0.0.1:0"]))
    try:
        start = time.monotonic()
        assert bus.run(lambda: False, timeout=0.25) is False
        assert 0.25 <= time.monotonic() - start < 0.6
        assert bus.run(lambda: True, timeout=0) is True
        flag = []
        bus.call_later(0.05, lambda: flag.append(1))
        assert bus.run(lambda: bool(flag), timeout=2) is True
    finally:
        bus.close()


def test_close_is_idempotent_and_publish_after_close_fails():
    bus = ZenohBus(session_config(listen=["tcp/127.0.0.1:0"]))
    bus.subscribe("t/x", lambda k, p: None)
    bus.declare_alive("t/alive/x")
    bus.publish("t/x", b"1")
    bus.close()
    bus.close()
    assert bus.closed
    with pytest.raises(BusError):
        bus.publish("t/x", b"2")


# -- other processes and topologies ----------------------------------------------------------


def test_spawned_process_publishes_to_parent():
    port = free_tcp_port()
    proc = hz.spawn_context().Process(target=hz.child_publisher, args=(port, 200))
    proc.start()  # before this process opens its session for the test
    try:
        with hz.listener(port) as bus:
            got = collect(bus, hz.DATA)
            assert bus.run(lambda: len(got) == 200, timeout=20), f"{len(got)} of 200"
            assert [int.from_bytes(p, "little") for _, p in got] == list(range(200))
            bus.publish(hz.DONE, b"")
            proc.join(10)
            assert proc.exitcode == 0
    finally:
        hz.stop_process(proc)


def test_clients_through_python_router():
    port = free_tcp_port()
    with hz.router(port):
        with hz.connector(port, mode="client") as a, hz.connector(port, mode="client") as b:
            at_a, at_b = collect(a, "t/to_a"), collect(b, "t/to_b")
            assert a.wait_for_subscribers("t/to_b", 5) and b.wait_for_subscribers("t/to_a", 5)
            for i in range(10):
                a.publish("t/to_b", bytes([i]))
                b.publish("t/to_a", bytes([i]))
            assert b.run(lambda: len(at_b) == 10, timeout=5)
            assert a.run(lambda: len(at_a) == 10, timeout=5)
            assert [p for _, p in at_b] == [bytes([i]) for i in range(10)]


@pytest.mark.parametrize("mode", ["peer", "client"])
def test_round_trip_between_processes(mode, capsys):
    """Measures (prints) the bus overhead; asserts only that every PONG came back."""
    port = free_tcp_port()
    proc = hz.spawn_context().Process(target=hz.child_echo, args=(port, mode))
    proc.start()
    try:
        if mode == "peer":
            with hz.listener(port) as bus:
                rtts = hz.ping_pong(bus, 2000)
                bus.publish(hz.STOP, b"")
        else:
            with hz.router(port), hz.connector(port, mode="client") as bus:
                rtts = hz.ping_pong(bus, 2000)
                bus.publish(hz.STOP, b"")
                proc.join(10)  # let the echo leave before the router goes
        with capsys.disabled():
            route = "peer to peer" if mode == "peer" else "clients via a Python router"
            print(f"\nZenohBus round trip, two processes, {route}: {hz.summary_us(rtts)}")
        assert len(rtts) == 2000
    finally:
        hz.stop_process(proc)


# -- hot subscriptions -----------------------------------------------------------------------


def test_hot_messages_arrive_in_order_on_the_run_thread():
    with hz.peer_pair() as (a, b):
        got, threads = [], set()

        def handler(key, payload):
            got.append((key, payload))
            threads.add(threading.get_ident())

        b.subscribe("t/hot/*", handler, hot=True)
        assert a.wait_for_subscribers("t/hot/x", 5)
        payloads = [i.to_bytes(2, "little") for i in range(300)] + [b""]  # an empty payload is a message too
        for payload in payloads:
            a.publish("t/hot/x", payload)
        assert b.run(lambda: len(got) == len(payloads), timeout=10)
        assert got == [("t/hot/x", p) for p in payloads]
        assert threads == {threading.get_ident()} and b.dropped == 0


def test_a_run_waiting_on_a_hot_key_wakes_for_everything_else():
    """Queued messages, liveliness, timers and calls from other threads end the wait at once, not
    at the next POLL."""
    with hz.peer_pair() as (a, b):
        events = []
        b.subscribe("t/hot", lambda k, p: events.append("hot"), hot=True)
        b.subscribe("t/cold", lambda k, p: events.append("cold"))
        b.watch_alive("t/alive/*", lambda k, alive: events.append("alive"))
        assert a.wait_for_subscribers("t/cold", 5)
        b.run(lambda: False, timeout=0.3)  # settle; run is now idle on the hot channel

        def waited(action, label) -> float:
            t0 = time.monotonic()
            action()
            assert b.run(lambda: label in events, timeout=2), events
            return time.monotonic() - t0

        assert waited(lambda: a.publish("t/cold", b"1"), "cold") < 0.5 * POLL
        assert waited(lambda: a.declare_alive("t/alive/a"), "alive") < 0.5 * POLL
        assert waited(lambda: b.call_later(0.01, lambda: events.append("timer")), "timer") < 0.01 + 0.5 * POLL
        later = threading.Timer(0.02, lambda: b.call_later(0.0, lambda: events.append("other thread")))
        later.start()
        assert waited(lambda: None, "other thread") < 0.02 + 0.5 * POLL
        a.publish("t/hot", b"2")
        assert b.run(lambda: "hot" in events, timeout=2)


def test_expect_names_the_hot_key_to_wait_on():
    with hz.peer_pair() as (a, b):
        got = []
        b.subscribe("t/first", lambda k, p: got.append(k), hot=True)
        b.subscribe("t/second", lambda k, p: got.append(k), hot=True)
        assert a.wait_for_subscribers("t/second", 5)
        b.run(lambda: False, timeout=0.2)
        b.expect("t/second")
        t0 = time.monotonic()
        a.publish("t/second", b"x")
        assert b.run(lambda: got == ["t/second"], timeout=2)
        assert time.monotonic() - t0 < 0.5 * POLL
        b.expect(None)
        a.publish("t/second", b"y")  # not waited on: read once run wakes (here at the latest after POLL)
        a.publish("t/first", b"z")
        assert b.run(lambda: len(got) == 3, timeout=2)
        assert sorted(got[1:]) == ["t/first", "t/second"]


# -- several nodes on one bus ----------------------------------------------------------------


def test_handlers_of_one_key_share_a_subscriber_and_each_get_every_message():
    with hz.peer_pair() as (a, b):
        got = {"hot1": [], "hot2": [], "cold1": [], "cold2": []}
        b.subscribe("t/hot", lambda k, p: got["hot1"].append(p), hot=True)
        b.subscribe("t/hot", lambda k, p: got["hot2"].append(p), hot=True)
        b.subscribe("t/cold", lambda k, p: got["cold1"].append(p))
        b.subscribe("t/cold", lambda k, p: got["cold2"].append(p))
        assert a.wait_for_subscribers("t/cold", 5) and a.wait_for_subscribers("t/hot", 5)
        for i in range(3):
            a.publish("t/hot", bytes([i]))
            a.publish("t/cold", bytes([i]))
        assert b.run(lambda: all(len(v) == 3 for v in got.values()), timeout=5), got
        b.run(lambda: False, timeout=0.2)  # nothing more comes
        assert all(v == [b"\x00", b"\x01", b"\x02"] for v in got.values()), got


def test_a_later_watcher_of_a_pattern_is_told_the_tokens_alive_then_every_change():
    with hz.peer_pair() as (a, b):
        first, later = [], []
        b.watch_alive("t/alive/*", lambda k, alive: first.append((k, alive)))
        a.declare_alive("t/alive/x")
        assert b.run(lambda: first == [("t/alive/x", True)], timeout=5), first
        b.watch_alive("t/alive/*", lambda k, alive: later.append((k, alive)))
        assert b.run(lambda: later == [("t/alive/x", True)], timeout=5), later
        a.declare_alive("t/alive/y")
        assert b.run(lambda: len(later) == 2, timeout=5)
        assert later[1] == ("t/alive/y", True) and first[1] == ("t/alive/y", True)


def _shared_pair(port: int) -> tuple[ZenohBus, ZenohBus]:
    shared = ZenohBus(session_config(listen=[hz.listen_endpoint(port)]), open_timeout=10, shared=True)
    return shared, hz.connector(port)


def test_a_shared_bus_hands_its_own_nodes_their_messages_and_peers_get_one_copy():
    """Two nodes of one process (a shared bus) and a node in another: a message published on
    the shared bus reaches each subscriber once, whether in the same process or not."""
    shared, other = _shared_pair(free_tcp_port())
    try:
        here1, here2, there = [], [], []
        shared.subscribe("t/plan/1", lambda k, p: here1.append(p), hot=True)
        shared.subscribe("t/plan/1", lambda k, p: here2.append(p), hot=True)
        other.subscribe("t/plan/1", lambda k, p: there.append(p), hot=True)
        assert shared.wait_for_subscribers("t/plan/1", 5)
        for i in range(5):
            shared.publish("t/plan/1", bytes([i]))
        assert shared.run(lambda: len(here1) == 5 and len(here2) == 5, timeout=5)
        assert other.run(lambda: len(there) == 5, timeout=5)
        shared.run(lambda: False, timeout=0.2)
        other.run(lambda: False, timeout=0.2)
        expected = [bytes([i]) for i in range(5)]
        assert here1 == expected and here2 == expected and there == expected
    finally:
        other.close()
        shared.close()


def test_a_shared_bus_wakes_at_once_for_a_message_on_any_key():
    """On a shared bus only the first hot key is read by run itself: a message on any other key
    that a node waits for ends the wait at once, whatever the last node asked to expect."""
    shared, other = _shared_pair(free_tcp_port())
    try:
        got = []
        shared.subscribe("t/release", lambda k, p: got.append(k), hot=True)
        shared.subscribe("t/plan/9", lambda k, p: got.append(k), hot=True)
        shared.subscribe("t/plan/8", lambda k, p: got.append(k), hot=True)
        assert other.wait_for_subscribers("t/plan/9", 5) and other.wait_for_subscribers("t/plan/8", 5)
        shared.expect("t/plan/9")  # ignored: it cannot name what every node waits for
        shared.run(lambda: False, timeout=0.3)
        for key in ("t/plan/8", "t/plan/9", "t/release"):
            t0 = time.monotonic()
            other.publish(key, b"x")
            assert shared.run(lambda key=key: got[-1:] == [key], timeout=2), got
            assert time.monotonic() - t0 < 0.5 * POLL, key
    finally:
        other.close()
        shared.close()
