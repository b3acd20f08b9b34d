"""End to end: what a sensor's certificate lets it do on a node that enforces the access control.

Real Zenoh sessions over TLS on loopback (tests/helpers/access_probe.py, in a process of its
own): a node configured as the coordinator's process configures itself (its certificate and the
``acl.json`` that ``dmpc certs`` generates), and a session that holds ``sensor-I``'s valid
certificate but applies no access control of its own, as a rogue sensor would. It publishes on
every key of the run, declares the liveliness tokens of other roles and subscribes to every key.

docs/security.md: a sensor may publish ``state/sensor-I`` and declare ``alive/sensor-I``, and is
sent ``inputs``, ``control`` and the tokens ``alive/*``; nothing else. The same probe against the
node without ``acl.json`` shows everything getting through: the rules, not the probe, stop it.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.e2e_helpers import ROOT, free_port, run_cli

pytestmark = pytest.mark.e2e

NAMES = ["1", "2", "3", "4"]
EVERY_KEY = sorted(["release", "control", "inputs", "telemetry", "state/plant"]
                   + [f"{kind}/{name}" for name in NAMES for kind in ("plan", "ready")]
                   + [f"state/sensor-{name}" for name in NAMES])
EVERY_ROLE = sorted(["coordinator", "plant", "agent-1"] + [f"sensor-{name}" for name in NAMES])


@pytest.fixture(scope="module")
def tls(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("certs") / "tls"
    res = run_cli("certs", str(directory), "--scenario", "scenarios/paper.yaml")
    assert res.returncode == 0, res.stderr
    return directory


def access(tls: Path, role: str, own: str, acl: bool = True) -> dict:
    """What reached the node and the probe holding ``role``'s certificate (tests/helpers/access_probe.py)."""
    cmd = [sys.executable, "-m", "tests.helpers.access_probe", "--tls", str(tls), "--role", role, "--own", own,
           "--port", str(free_port()), "--names", ",".join(NAMES), *([] if acl else ["--no-acl"])]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert res.returncode == 0, res.stderr[-3000:]
    line = next(line for line in res.stdout.splitlines() if line.startswith("ACCESS "))
    return json.loads(line[len("ACCESS "):])


@pytest.mark.parametrize("name", ["1", "3"])
def test_a_sensor_publishes_its_own_state_and_is_sent_inputs_and_control_only(tls, name):
    seen = access(tls, f"sensor-{name}", f"state/sensor-{name}")
    # of everything it put (other sensors' states, the plant's, plans, ready, release, control,
    # inputs, telemetry), only its own state reached the node
    assert seen["node_received"] == [f"state/sensor-{name}"], seen
    # of the tokens it declared (the plant's, agent 1's, the other sensors'), only its own
    assert seen["node_saw_alive"] == sorted(["coordinator", f"sensor-{name}"]), seen
    # it subscribed to every key: the node sent it the inputs and Stop, nothing else
    assert seen["probe_received"] == ["control", "inputs"], seen
    # a subscriber to the whole run (dmpc/<run>/**) is refused as a whole (docs/protocol.md)
    assert seen["probe_received_wide"] == [], seen
    # and it sees the coordinator's token (its own come back to it from its own session)
    assert "coordinator" in seen["probe_saw_alive"], seen


def test_without_the_access_control_the_same_probe_gets_everything_through(tls):
    seen = access(tls, "sensor-3", "state/sensor-3", acl=False)
    assert seen["node_received"] == EVERY_KEY, seen
    assert seen["probe_received"] == seen["probe_received_wide"] == EVERY_KEY, seen
    assert seen["node_saw_alive"] == EVERY_ROLE, seen
