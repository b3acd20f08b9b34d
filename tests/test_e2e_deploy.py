"""End to end through the TCP delay relay: the paper's example with a real link delay.

Topology::

    agent 1..4 (client) --tcp--> dmpc relay (hold 3 ± 1 ms) --tcp--> plant (Zenoh router)

The plant's session is a Zenoh router listening on one port; ``dmpc relay`` listens on a second
port and forwards to the first; the agents run in **client mode** and are given only the
relay's port. Client mode is the choice because a client opens no link but the one it is
given, and a router forwards between its clients: every message, plant to agent and agent to
agent alike, crosses the relay (an agent's plan crosses it twice on its way to a neighbour).
Peers would instead learn each other's locators by gossip and link to each other directly, so
agent-to-agent traffic would bypass the relay and only part of the run would see the delay.
The test checks this: every TCP connection an agent holds goes to the relay's port.

In lockstep mode a delay changes when plans arrive, not what they are, so the trajectory
equals the in-process one (``dmpc simulate``) to 1e-9.
"""
from __future__ import annotations

import json
import re
import signal

import numpy as np
import psutil
import pytest

from tests.e2e_helpers import free_port, max_abs_diff, run_cli, step_lines, wait_for

pytestmark = pytest.mark.e2e

DELAY_MS, JITTER_MS = 3.0, 1.0


def _listening(pid: int, port: int) -> bool:
    try:
        conns = psutil.Process(pid).net_connections(kind="tcp")
    except psutil.NoSuchProcess:
        return False
    return any(c.status == psutil.CONN_LISTEN and c.laddr.port == port for c in conns)


def _remote_ports(pid: int) -> set[int]:
    try:
        conns = psutil.Process(pid).net_connections(kind="tcp")
    except psutil.NoSuchProcess:
        return set()
    return {c.raddr.port for c in conns if c.raddr and c.status == psutil.CONN_ESTABLISHED}


def test_paper_through_delay_relay_equals_simulate(procs, tmp_path):
    sim, out = tmp_path / "sim", tmp_path / "out"
    res = run_cli("simulate", "scenarios/paper.yaml", "--out", str(sim), "--quiet")
    assert res.returncode == 0, res.stderr
    plant_port, relay_port = free_port(), free_port()
    while relay_port == plant_port:
        relay_port = free_port()
    common = ["--run-id", "relayed", "--startup-timeout", "60", "--design", str(sim / "design.json")]

    plant = procs.start("plant", "scenarios/paper.yaml", "--out", str(out), "--quiet", "--mode", "router",
                        "--listen", f"tcp/127.0.0.1:{plant_port}", *common, log="plant.log")
    relay = procs.start("relay", "--listen", f"127.0.0.1:{relay_port}", "--to", f"127.0.0.1:{plant_port}",
                        "--delay", str(DELAY_MS), "--jitter", str(JITTER_MS), "--seed", "1", log="relay.log")
    assert wait_for(lambda: _listening(plant.pid, plant_port), timeout=60), procs.log(plant)
    assert wait_for(lambda: _listening(relay.pid, relay_port), timeout=30), procs.log(relay)
    agents = [procs.start("agent", "scenarios/paper.yaml", "--id", str(i), "--mode", "client",
                          "--connect", f"tcp/127.0.0.1:{relay_port}", *common, log=f"agent{i}.log")
              for i in range(1, 5)]

    # while the run goes on, every link an agent holds ends at the relay
    seen: set[int] = set()
    assert wait_for(lambda: step_lines(out) >= 1 or plant.poll() is not None, timeout=90), procs.log(plant)
    for a in agents:
        seen |= _remote_ports(a.pid)

    plant.wait(timeout=120)
    for a in agents:
        a.wait(timeout=20)
    assert plant.returncode == 0, procs.log(plant)
    assert all(a.returncode == 0 for a in agents), [procs.log(a) for a in agents]
    relay.send_signal(signal.SIGTERM)
    relay.wait(timeout=5)
    assert relay.returncode == 0, procs.log(relay)

    assert seen == {relay_port}, f"agents linked to ports {seen}, not only to the relay {relay_port}"
    stats = re.search(r"relay stopped: (\d+) connections \((\d+) without target\)", procs.log(relay))
    assert stats and int(stats[1]) >= 4 and stats[2] == "0", procs.log(relay)

    assert max_abs_diff(sim, out) <= 1e-9
    summary = json.loads((out / "summary.json").read_text())
    assert summary["feasible"] and summary["fallbacks"] == 0
    # the delay was real: a plan takes at least one hold (delay - jitter) to reach the plant
    latency = np.load(out / "trajectory.npz")["latency"]
    assert np.nanmin(latency) >= (DELAY_MS - JITTER_MS) / 1000, np.nanmin(latency)
    step = np.load(out / "trajectory.npz")["step_time"]
    print(f"relayed run: plan latency min {np.nanmin(latency) * 1000:.2f} ms, median "
          f"{np.nanmedian(latency) * 1000:.2f} ms; step time median {np.median(step) * 1000:.1f} ms; "
          f"{procs.log(relay).strip().splitlines()[-1]}")
