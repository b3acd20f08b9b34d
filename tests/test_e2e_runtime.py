"""End to end: real processes over Zenoh on loopback (multicast off, a free port per test)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest

from tests.e2e_helpers import (DMPC, ROOT, free_port, max_abs_diff, pid_alive, run_cli, step_lines,
                               wait_for)

pytestmark = pytest.mark.e2e


@pytest.mark.parametrize("scenario, extra", [("scenarios/paper.yaml", []),
                                             ("scenarios/chain.yaml", ["--set", "family.M=8"])])
def test_run_equals_simulate(tmp_path, scenario, extra):
    sim, multi = tmp_path / "sim", tmp_path / "multi"
    res = run_cli("simulate", scenario, "--out", str(sim), "--quiet", *extra)
    assert res.returncode == 0, res.stderr
    res = run_cli("run", scenario, "--out", str(multi), "--quiet", *extra)
    assert res.returncode == 0, res.stderr + res.stdout
    assert max_abs_diff(sim, multi) <= 1e-9
    summary = json.loads((multi / "summary.json").read_text())
    assert summary["feasible"] and summary["fallbacks"] == 0
    assert summary["runtime"] == "multi-process"
    assert "run folder:" in res.stdout
    # same files, same keys
    files = {p.name for p in sim.iterdir()}
    assert files <= {p.name for p in multi.iterdir()}
    assert set(json.loads((sim / "summary.json").read_text())) == set(summary)
    assert set(json.loads((sim / "design.json").read_text())) == set(json.loads((multi / "design.json").read_text()))
    assert set(np.load(sim / "trajectory.npz").files) == set(np.load(multi / "trajectory.npz").files)
    processes = json.loads((multi / "processes.json").read_text())
    assert set(processes) == {"plant"} | {f"agent-{i}" for i in (range(1, 5) if "paper" in scenario else range(1, 9))}
    assert not any(pid_alive(pid) for pid in processes.values())


def test_sigint_mid_run_leaves_no_process_and_keeps_steps(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(DMPC + ["run", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                                    "--set", "options.mode=realtime", "--set", "options.dt=0.2", "--steps", "40"],
                            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert wait_for(lambda: step_lines(out) >= 3, timeout=60), "the run did not get going"
        processes = json.loads((out / "processes.json").read_text())
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        proc.wait(timeout=10)
        assert time.monotonic() - t0 < 6
        assert proc.returncode == 130
        assert wait_for(lambda: not any(pid_alive(pid) for pid in processes.values()), timeout=2)
        completed = step_lines(out)
        assert 3 <= completed < 40
        summary = json.loads((out / "summary.json").read_text())
        assert summary["steps"] == completed
        assert summary.get("aborted")
        assert np.load(out / "trajectory.npz")["x"].shape[0] == completed + 1
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_agent_without_plant_exits_with_message(procs):
    port = free_port()
    t0 = time.monotonic()
    agent = procs.start("agent", "scenarios/paper.yaml", "--id", "1", "--listen", f"tcp/127.0.0.1:{port}",
                        "--startup-timeout", "3")
    agent.wait(timeout=30)
    elapsed = time.monotonic() - t0
    assert agent.returncode == 1
    text = procs.log(agent)
    assert "no release from the plant within 3 s" in text and "plant" in text
    assert "Traceback" not in text
    assert elapsed < 15


def test_agent_with_unreachable_endpoint_exits_with_message(procs):
    port = free_port()  # nothing listens here
    agent = procs.start("agent", "scenarios/paper.yaml", "--id", "1", "--connect", f"tcp/127.0.0.1:{port}",
                        "--startup-timeout", "3")
    agent.wait(timeout=30)
    assert agent.returncode == 1
    text = procs.log(agent)
    assert f"127.0.0.1:{port}" in text and "Traceback" not in text


def test_plant_that_never_sees_an_agent_exits_with_message(procs, tmp_path):
    port = free_port()
    plant = procs.start("plant", "scenarios/paper.yaml", "--out", str(tmp_path / "out"), "--listen",
                        f"tcp/127.0.0.1:{port}", "--startup-timeout", "3", "--quiet")
    plant.wait(timeout=30)
    assert plant.returncode == 1
    text = procs.log(plant)
    assert "agents 1, 2, 3, 4 not ready within 3 s" in text and "Traceback" not in text
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["steps"] == 0 and "not ready" in summary["failure"]


def _manual_run(procs, tmp_path, plant_net, agent_net, router=None):
    out = tmp_path / "out"
    if router:
        procs.start("router", "--listen", router, log="router.log")
    plant = procs.start("plant", "scenarios/paper.yaml", "--out", str(out), "--quiet", "--run-id", "t1",
                        "--startup-timeout", "60", *plant_net, log="plant.log")
    agents = [procs.start("agent", "scenarios/paper.yaml", "--id", str(i), "--run-id", "t1",
                          "--startup-timeout", "60", *agent_net, log=f"agent{i}.log") for i in range(1, 5)]
    plant.wait(timeout=120)
    for a in agents:
        a.wait(timeout=20)
    assert plant.returncode == 0, procs.log(plant)
    assert all(a.returncode == 0 for a in agents), [procs.log(a) for a in agents]
    return out


def test_clients_through_router(procs, tmp_path, paper_simulated):
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    net = ["--mode", "client", "--connect", ep]
    out = _manual_run(procs, tmp_path, net, net, router=ep)
    assert max_abs_diff(paper_simulated, out) <= 1e-9


def test_peers_only(procs, tmp_path, paper_simulated):
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    out = _manual_run(procs, tmp_path, ["--listen", ep], ["--connect", ep, "--listen", "tcp/127.0.0.1:0"])
    assert max_abs_diff(paper_simulated, out) <= 1e-9


def test_run_refuses_used_folder_with_exit_2(tmp_path, paper_simulated):
    res = run_cli("run", "scenarios/paper.yaml", "--out", str(paper_simulated), "--quiet")
    assert res.returncode == 2
    assert res.stderr.startswith("error:") and "already holds a run" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.skipif(os.cpu_count() is None, reason="needs cpu count")
def test_failed_child_stops_every_process(tmp_path):
    """A child that fails (here: an agent that cannot load its design) stops the whole run."""
    out = tmp_path / "run"
    proc = subprocess.Popen(DMPC + ["run", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                                    "--set", "options.mode=realtime", "--set", "options.dt=0.2", "--steps", "100"],
                            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert wait_for(lambda: step_lines(out) >= 2, timeout=60)
        processes = json.loads((out / "processes.json").read_text())
        os.kill(processes["agent-3"], signal.SIGKILL)
        proc.wait(timeout=15)
        assert proc.returncode == 1
        assert "agent-3" in proc.stderr.read().decode()
        assert wait_for(lambda: not any(pid_alive(pid) for pid in processes.values()), timeout=2)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
