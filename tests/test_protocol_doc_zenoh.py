"""What docs/protocol.md tells a plant of its own to do with Zenoh, tried with real sessions.

The client settings of "Connecting" (taken from the page as written) wait for a coordinator that
starts listening after the plant, and fail after their timeout; the two ways of "Liveliness" read
a token that existed before; under the access control of "Access control", a wildcard
subscription of the plant's role receives nothing while the exact keys do. examples/outside_plant.py
uses the same settings. Loopback only, multicast off, a free port per test.
"""
from __future__ import annotations

import importlib.util
import json
import re
import threading
import time

import pytest
import zenoh

from dmpc.bus import keys
from dmpc.bus.session import session_config
from dmpc.bus.zenoh_bus import ZenohBus
from dmpc.scenario import build_system, load_scenario
from dmpc.security.certs import make_run_security
from dmpc.security.files import node_security
from tests.e2e_helpers import ROOT, free_port

pytestmark = pytest.mark.e2e

DOC = ROOT / "docs" / "protocol.md"
EXAMPLE = ROOT / "examples" / "outside_plant.py"
RUN = "doc"


def documented_client_settings() -> str:
    """The JSON5 block of the page's "Connecting" section."""
    section = DOC.read_text().split("\n## Connecting\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```json5\n(.*?)\n```", section, flags=re.S)
    assert len(blocks) == 1, "docs/protocol.md, Connecting: expected one json5 block of Zenoh settings"
    return blocks[0]


def client(endpoint: str, **replace: str) -> zenoh.Config:
    """The documented settings for ``endpoint``, with ``replace`` (a JSON5 value per key) applied."""
    text = documented_client_settings().replace("tcp/HOST:PORT", endpoint)
    for key, value in replace.items():
        text, n = re.subn(rf"\b{key}: [^,\n]+", f"{key}: {value}", text)
        assert n == 1, key
    return zenoh.Config.from_json5(text)


def listener(endpoint: str) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return zenoh.open(config)


# ------------------------------------------------------------------------------------ connecting
def test_a_plant_with_the_documented_settings_waits_for_a_coordinator_that_listens_later():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opened: list = []
    failed: list = []

    def open_plant() -> None:
        started = time.monotonic()
        try:
            opened.append((zenoh.open(client(endpoint)), time.monotonic() - started))
        except zenoh.ZError as exc:
            failed.append(exc)

    plant = threading.Thread(target=open_plant)
    plant.start()
    time.sleep(2.5)  # the plant has started first: its first tries find nothing listening
    assert plant.is_alive() and not failed, failed
    coordinator = listener(endpoint)
    try:
        plant.join(timeout=15)
        assert not plant.is_alive() and not failed, failed
        session, waited = opened[0]
        got = []
        coordinator.declare_subscriber(f"dmpc/{RUN}/state/plant", lambda sample: got.append(sample))
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:  # the subscription travels to the client first
            session.put(f"dmpc/{RUN}/state/plant", b"x")
            time.sleep(0.2)
        session.close()
        assert got and 2.5 <= waited < 10
    finally:
        coordinator.close()


def test_the_documented_settings_fail_after_their_timeout_and_the_zenoh_default_at_once():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(client(endpoint, timeout_ms="1500"))
    assert 1.4 <= time.monotonic() - started < 8
    started = time.monotonic()
    with pytest.raises(zenoh.ZError, match="Unable to connect"):  # what the page warns of: no timeout_ms
        zenoh.open(client(endpoint, timeout_ms="0"))
    assert time.monotonic() - started < 1.0


def test_the_example_opens_its_session_with_the_documented_settings():
    spec = importlib.util.spec_from_file_location("outside_plant", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    endpoint = "tcp/127.0.0.1:7447"
    documented = client(endpoint)
    used = example.zenoh_config(endpoint, None, "plant", 60.0)
    for key in ("mode", "connect", "scouting/multicast/enabled"):
        assert json.loads(used.get_json(key)) == json.loads(documented.get_json(key)), key


# ------------------------------------------------------------------------------------ liveliness
def test_both_documented_ways_read_a_token_that_already_exists():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    coordinator = listener(endpoint)
    token = coordinator.liveliness().declare_token(f"dmpc/{RUN}/alive/coordinator")
    plant = zenoh.open(client(endpoint))
    try:
        # the token is declared before the plant looks: wait until the plant's session knows it
        # (a get answers once its link to the coordinator is up, however loaded the machine)
        found: list[str] = []
        deadline = time.monotonic() + 30
        while not found and time.monotonic() < deadline:
            found = [str(r.ok.key_expr) for r in plant.liveliness().get(f"dmpc/{RUN}/alive/*", timeout=1.0)
                     if r.ok is not None]
        assert found == [f"dmpc/{RUN}/alive/coordinator"]
        seen: list = []
        history = plant.liveliness().declare_subscriber(
            f"dmpc/{RUN}/alive/coordinator", lambda s: seen.append((str(s.key_expr), s.kind)), history=True)
        without: list = []
        plain = plant.liveliness().declare_subscriber(f"dmpc/{RUN}/alive/*", lambda s: without.append(s))
        deadline = time.monotonic() + 30
        while not seen and time.monotonic() < deadline:
            time.sleep(0.05)
        assert seen == [(f"dmpc/{RUN}/alive/coordinator", zenoh.SampleKind.PUT)]
        replies = list(plant.liveliness().get(f"dmpc/{RUN}/alive/*", timeout=10.0))
        assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [f"dmpc/{RUN}/alive/coordinator"]
        assert without == []  # why the page says so: without history, a token that exists is not reported
        history.undeclare()
        plain.undeclare()
    finally:
        token.undeclare()
        plant.close()
        coordinator.close()


# -------------------------------------------------------------------------------- access control
def test_under_access_control_a_wildcard_subscription_of_the_plant_receives_nothing(tmp_path):
    system = build_system(load_scenario(ROOT / "scenarios" / "paper.yaml"))
    tls = tmp_path / "tls"
    make_run_security(tls, system)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    files, acl = node_security(tls, keys.COORDINATOR_ROLE)
    coordinator = ZenohBus(session_config(listen=[endpoint], tls=files, acl=acl))
    settings = client(endpoint)
    for key, value in {"root_ca_certificate": "ca.pem", "connect_certificate": "plant.pem",
                       "connect_private_key": "plant.key"}.items():
        settings.insert_json5(f"transport/link/tls/{key}", json.dumps(str(tls / value)))
    settings.insert_json5("transport/link/tls/enable_mtls", "true")

    def received(subscriptions: list[str]) -> dict[str, list[str]]:
        plant = zenoh.open(settings)
        got: dict[str, list[str]] = {expr: [] for expr in subscriptions}
        for expr in subscriptions:
            plant.declare_subscriber(expr, lambda s, expr=expr: got[expr].append(keys.last_chunk(str(s.key_expr))))
        try:
            deadline = time.monotonic() + 4
            while time.monotonic() < deadline:
                coordinator.publish(keys.inputs(RUN), b"u")
                coordinator.publish(keys.control(RUN), b"s")
                coordinator.run(until=lambda: False, timeout=0.2)
        finally:
            plant.close()
        return got

    try:
        wide = received([f"dmpc/{RUN}/**", f"dmpc/{RUN}/*"])
        assert wide == {f"dmpc/{RUN}/**": [], f"dmpc/{RUN}/*": []}
        exact = received([f"dmpc/{RUN}/inputs", f"dmpc/{RUN}/control"])
        assert set(exact[f"dmpc/{RUN}/inputs"]) == {"inputs"} and set(exact[f"dmpc/{RUN}/control"]) == {"control"}
    finally:
        coordinator.close()
