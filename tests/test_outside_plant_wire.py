"""examples/outside_plant.py against a coordinator played by this test over Zenoh.

The test holds the coordinator's token and speaks dmpc's codec (``bus.codec``): what the example
sends must decode there and pass the coordinator's state checks (``plant.state_inbox``), its
states must be dmpc's plant dynamics exactly, and it must follow the rules of the plant's side
of docs/protocol.md (repeats of x(0), one application per step, answers to repeated inputs, the
other steps ignored, Stop and a lost coordinator ending it).
"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from dmpc.bus import keys
from dmpc.bus.codec import DecodeError, VersionMismatch, decode, encode
from dmpc.bus.messages import Inputs, State, Stop
from dmpc.bus.session import session_config
from dmpc.bus.zenoh_bus import ZenohBus
from dmpc.plant.dynamics import Plant
from dmpc.plant.state_inbox import StateInbox
from dmpc.scenario import build_system, load_scenario
from dmpc.security.certs import make_run_security
from dmpc.security.files import node_security
from tests.e2e_helpers import ROOT, free_port
from tests.helpers.bad_plant import FORGED_REASON

pytestmark = pytest.mark.e2e

EXAMPLE = ROOT / "examples" / "outside_plant.py"
RUN = "wire"


@pytest.fixture(scope="module")
def system():
    return build_system(load_scenario(ROOT / "scenarios" / "paper.yaml"))


class FakeCoordinator:
    """A Zenoh peer listening on a free port that holds the coordinator's token and records states."""

    def __init__(self, system, tls: Path | None = None, port: int | None = None) -> None:
        self.system = system
        self.endpoint = f"{'tls' if tls else 'tcp'}/127.0.0.1:{port or free_port()}"
        files, acl = node_security(tls, keys.COORDINATOR_ROLE) if tls else (None, None)
        self.bus = ZenohBus(session_config(listen=[self.endpoint], tls=files, acl=acl))
        self.states: list[tuple[str, State]] = []
        self.undecodable: list[tuple[str, DecodeError]] = []
        self.strict = True
        self.alive: set[str] = set()
        self.bus.subscribe(keys.state_prefix(RUN), self._on_state)
        self.bus.watch_alive(keys.alive_prefix(RUN), self._on_alive)
        self.foreign: list[str] = []  # keys of messages that only the coordinator or an agent may send
        for key in (keys.release(RUN), keys.plan(RUN, "*"), keys.ready(RUN, "*"), keys.control(RUN)):
            self.bus.subscribe(key, self._on_foreign)
        self.bus.declare_alive(keys.alive(RUN, keys.COORDINATOR_ROLE))

    def _on_state(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload)
        except DecodeError as exc:
            self.undecodable.append((keys.last_chunk(key), exc))
            return
        assert isinstance(msg, State)
        self.states.append((keys.last_chunk(key), msg))

    def _on_foreign(self, key: str, payload: bytes) -> None:
        if key != keys.control(RUN) or decode(payload).reason == FORGED_REASON:  # not this test's own Stop
            self.foreign.append(key)

    def _on_alive(self, key: str, alive: bool) -> None:
        (self.alive.add if alive else self.alive.discard)(keys.last_chunk(key))

    def wait(self, predicate, timeout: float = 10.0) -> bool:
        return self.bus.run(until=predicate, timeout=timeout)

    def send_inputs(self, k: int, u: np.ndarray) -> None:
        parts = {s.name: u[self.system.us(i)] for i, s in enumerate(self.system.subsystems)}
        self.bus.publish(keys.inputs(RUN), encode(Inputs(run=RUN, k=k, u=parts)))

    def stop(self, reason: str, k: int) -> None:
        self.bus.publish(keys.control(RUN), encode(Stop(run=RUN, k=k, reason=reason)))

    def of_step(self, k: int) -> list[tuple[str, State]]:
        return [(source, msg) for source, msg in self.states if msg.k == k]

    def assembled(self, k: int) -> np.ndarray | None:
        """x(k) as the coordinator's inbox assembles it from what arrived, or None if incomplete."""
        inbox, checker = StateInbox(self.system), StateInbox(self.system)
        inbox.expect(k)
        checker.expect(k)
        measured = None
        for source, msg in self.of_step(k):
            assert checker.problem(source, msg) is None, (source, msg)  # every copy passes the checks
            measured = inbox.take(msg) if measured is None else measured
        return None if measured is None else measured.x


@pytest.fixture
def coordinator(system):
    fake = FakeCoordinator(system)
    yield fake
    fake.bus.close()
    if fake.strict:  # whatever the example sent decodes with dmpc's codec
        assert fake.undecodable == []


@pytest.fixture
def start(tmp_path):
    started = []

    def start(endpoint: str, *args: str) -> subprocess.Popen:
        err = open(tmp_path / f"plant{len(started)}.err", "w+b")
        proc = subprocess.Popen([sys.executable, str(EXAMPLE), "--connect", endpoint, "--run-id", RUN,
                                 "--startup-timeout", "20", *args], cwd=ROOT, stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=err, text=True)
        proc.err = err
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.err.close()


def finish(proc: subprocess.Popen, timeout: float = 15.0) -> tuple[int, str, str]:
    out, _ = proc.communicate(timeout=timeout)
    proc.err.seek(0)
    return proc.returncode, out, proc.err.read().decode(errors="replace")


def inputs_of(k: int) -> np.ndarray:
    """Some inputs u(k), shape (4,), different at every step."""
    return np.array([0.5, -1.25, 2.0, -0.75]) * (1.0 + 0.1 * k)


def test_whole_plant_follows_the_rules_and_the_dynamics(coordinator, start, system):
    proc = start(coordinator.endpoint)
    assert coordinator.wait(lambda: len(coordinator.of_step(0)) >= 2), "x(0) was not sent, or not repeated"
    assert "plant" in coordinator.alive
    t_first = time.monotonic()
    reference = Plant(system)
    assert np.array_equal(coordinator.assembled(0), reference.x)
    assert {source for source, _ in coordinator.states} == {"plant"}

    coordinator.send_inputs(0, inputs_of(0))
    assert coordinator.wait(lambda: coordinator.of_step(1))
    expected = reference.step(inputs_of(0))
    assert np.array_equal(coordinator.assembled(1), expected)  # bit for bit: the same model and arithmetic
    first_copies = len(coordinator.of_step(0))

    coordinator.send_inputs(0, inputs_of(0))  # a repeat of the step just applied: the same answer again
    assert coordinator.wait(lambda: len(coordinator.of_step(1)) == 2)
    assert np.array_equal(coordinator.of_step(1)[1][1].x["1"], coordinator.of_step(1)[0][1].x["1"])

    coordinator.send_inputs(5, inputs_of(5))  # another step: ignored
    coordinator.send_inputs(0, inputs_of(3))  # different inputs for the step applied: the same answer, not applied
    assert coordinator.wait(lambda: len(coordinator.of_step(1)) == 3)
    coordinator.wait(lambda: False, timeout=1.0)
    assert {msg.k for _, msg in coordinator.states} == {0, 1}
    assert np.array_equal(coordinator.assembled(1), expected)
    assert len(coordinator.of_step(0)) == first_copies  # x(0) is no longer repeated once step 0 is applied
    assert first_copies <= 2 + (time.monotonic() - t_first) / 0.5

    coordinator.send_inputs(1, inputs_of(1))
    assert coordinator.wait(lambda: coordinator.of_step(2))
    assert np.array_equal(coordinator.assembled(2), reference.step(inputs_of(1)))

    coordinator.stop("finished", 2)
    code, out, err = finish(proc)
    assert code == 0, err
    assert out.strip().splitlines() == ["outside plant (plant): finished after 2 steps"]
    assert "Traceback" not in err


def test_a_plant_started_before_the_coordinator_listens_joins_when_it_does(start, system):
    """docs/protocol.md, "Connecting": the plant keeps trying to reach the endpoint."""
    port = free_port()
    proc = start(f"tcp/127.0.0.1:{port}")
    time.sleep(3.0)  # the plant starts first: nothing listens on the port yet
    assert proc.poll() is None, finish(proc)
    coordinator = FakeCoordinator(system, port=port)
    try:
        assert coordinator.wait(lambda: coordinator.of_step(0), timeout=20), "x(0) never came"
        reference = Plant(system)
        coordinator.send_inputs(0, inputs_of(0))
        assert coordinator.wait(lambda: coordinator.of_step(1))
        assert np.array_equal(coordinator.assembled(1), reference.step(inputs_of(0)))
        coordinator.stop("finished", 1)
        code, out, err = finish(proc)
        assert code == 0, err
        assert out.strip() == "outside plant (plant): finished after 1 steps"
    finally:
        coordinator.bus.close()


def test_sensors_report_their_own_subsystems_only(coordinator, start, system):
    first = start(coordinator.endpoint, "--sensor", "1", "--sensor", "2")
    second = start(coordinator.endpoint, "--sensor", "3", "--sensor", "4")
    assert coordinator.wait(lambda: coordinator.assembled(0) is not None)
    assert {"sensor-1", "sensor-2", "sensor-3", "sensor-4"} <= coordinator.alive and "plant" not in coordinator.alive
    reference = Plant(system)
    assert np.array_equal(coordinator.assembled(0), reference.x)
    for k in range(3):
        coordinator.send_inputs(k, inputs_of(k))
        assert coordinator.wait(lambda k=k: coordinator.assembled(k + 1) is not None)
        assert np.array_equal(coordinator.assembled(k + 1), reference.step(inputs_of(k)))
    for source, msg in coordinator.states:
        assert source.startswith("sensor-") and list(msg.x) == [source[len("sensor-"):]], (source, msg)
    coordinator.stop("failed: a test", 3)
    for proc, who in ((first, "sensor-1 sensor-2"), (second, "sensor-3 sensor-4")):
        code, out, err = finish(proc)
        assert code == 1, err
        assert out.strip() == f"outside plant ({who}): the coordinator stopped the run after 3 steps (failed: a test)"


def test_another_protocol_version_is_dropped_with_both_versions_named(coordinator, start):
    proc = start(coordinator.endpoint)
    assert coordinator.wait(lambda: coordinator.of_step(0))
    body = msgpack.unpackb(encode(Inputs(run=RUN, k=0, u={n: np.zeros(1) for n in "1234"})), raw=False)
    del body["protocol"]
    body["schema"] = 2  # how protocol version 2 wrote its version
    coordinator.bus.publish(keys.inputs(RUN), msgpack.packb(body, use_bin_type=True))
    coordinator.wait(lambda: False, timeout=1.0)
    assert not coordinator.of_step(1), "inputs of another protocol version were applied"
    coordinator.stop("finished", 0)
    code, out, err = finish(proc)
    assert code == 0
    assert "dropped a message on inputs: protocol version 2; this process speaks protocol version 3" in err


def test_a_lost_coordinator_ends_the_plant(coordinator, start):
    proc = start(coordinator.endpoint)
    assert coordinator.wait(lambda: coordinator.of_step(0))
    coordinator.send_inputs(0, inputs_of(0))
    assert coordinator.wait(lambda: coordinator.of_step(1))
    coordinator.bus.close()
    t0 = time.monotonic()
    code, out, err = finish(proc)
    assert code == 1, err
    assert 1.0 < time.monotonic() - t0 < 10
    assert out.strip() == "outside plant (plant): lost the coordinator after 1 steps (its token was gone for 1.5 s)"


def test_bad_arguments_exit_2_naming_the_problem(start):
    for args, words in ((["--sensor", "7"], "--sensor '7': the subsystems are 1, 2, 3, 4"),
                        (["--tls", "/nonexistent"], "with --tls the endpoint must be tls/HOST:PORT")):
        code, out, err = finish(start("tcp/127.0.0.1:9", *args))
        assert code == 2 and words in err and "Traceback" not in err, err


@pytest.mark.parametrize("mode, sensor", [("shape", None), ("nan", None), ("version", None), ("shape", "2")])
def test_the_bad_plants_send_what_the_coordinator_drops(coordinator, tmp_path, mode, sensor):
    """tests/helpers/bad_plant.py (used by the end-to-end tests) really sends the fault it names."""
    args = ["--sensor", sensor] if sensor else []
    coordinator.strict = False
    proc = subprocess.Popen([sys.executable, "-m", "tests.helpers.bad_plant", mode, "--connect", coordinator.endpoint,
                             "--run-id", RUN, "--startup-timeout", "20", *args], cwd=ROOT,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert coordinator.wait(lambda: coordinator.states or coordinator.undecodable)
        source = f"sensor-{sensor}" if sensor else "plant"
        if mode == "shape":
            inbox = StateInbox(coordinator.system)
            inbox.expect(0)
            assert [s for s, _ in coordinator.states][:1] == [source]
            assert inbox.problem(source, coordinator.states[0][1]) == \
                "the state of subsystem 2 has shape (3,), expected (2,)"
        else:
            got, exc = coordinator.undecodable[0]
            assert got == source and not coordinator.states
            if mode == "nan":
                assert str(exc) == "x[2]: non-finite values"
            else:
                assert isinstance(exc, VersionMismatch) and exc.version == 2
        coordinator.stop("finished", 0)
        out, err = proc.communicate(timeout=15)
        assert proc.returncode == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("acl", [True, False])
def test_with_tls_the_plant_role_may_publish_its_state_and_nothing_else(system, tmp_path, acl):
    """Over TLS with the plant's certificate, a plant that also sends releases, plans, ready
    messages and Stop at every step gets only its states through the access control; without
    acl.json the same messages arrive (so the check can fail)."""
    tls = tmp_path / "tls"
    make_run_security(tls, system)
    if not acl:
        (tls / "acl.json").unlink()
    coordinator = FakeCoordinator(system, tls=tls)
    proc = subprocess.Popen([sys.executable, "-m", "tests.helpers.bad_plant", "rogue", "--connect",
                             coordinator.endpoint, "--run-id", RUN, "--tls", str(tls), "--startup-timeout", "20"],
                            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert coordinator.wait(lambda: coordinator.of_step(0)), "no x(0) over TLS"
        reference = Plant(system)
        for k in range(3):
            coordinator.send_inputs(k, inputs_of(k))
            assert coordinator.wait(lambda k=k: coordinator.assembled(k + 1) is not None)
            assert np.array_equal(coordinator.assembled(k + 1), reference.step(inputs_of(k)))
        coordinator.wait(lambda: False, timeout=1.0)
        coordinator.stop("finished", 3)
        out, err = proc.communicate(timeout=15)
        assert proc.returncode == 0, err
        assert "ROGUE SENT 12" in out  # four forgeries at each of 3 steps
        if acl:
            assert coordinator.foreign == []
        else:
            assert {keys.last_chunk(k) for k in coordinator.foreign} == {"release", "1", "control"}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        coordinator.bus.close()


def test_a_plant_that_never_sees_a_coordinator_gives_up_after_its_startup_timeout(start):
    """docs/protocol.md: a plant waits --startup-timeout for the coordinator's token, then exits 1
    naming the run; a peer that listens but holds no coordinator token does not count."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = ZenohBus(session_config(listen=[endpoint]))
    try:
        t0 = time.monotonic()
        proc = start(endpoint, "--startup-timeout", "2")
        code, out, err = finish(proc)
        elapsed = time.monotonic() - t0
    finally:
        bus.close()
    assert code == 1, out + err
    assert out.strip() == f"outside plant (plant): no coordinator of run {RUN!r} within 2 s"
    assert 2.0 <= elapsed < 10.0
