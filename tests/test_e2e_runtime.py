"""End to end: real processes over Zenoh on loopback (multicast off, a free port per test)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest

from tests.e2e_helpers import DMPC, ROOT, free_port, max_abs_diff, pid_alive, run_cli, step_lines, wait_for

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
    launcher_only = {"launcher", "agent_reports_missing", "startup_s"}  # what dmpc run adds about its processes
    assert set(json.loads((sim / "summary.json").read_text())) == set(summary) - launcher_only
    assert summary["launcher"] == {"restarts": {}, "lost": [], "crashes": {}}
    assert 0 < summary["startup_s"] < 60  # processes started to the first release
    assert summary["agent_reports_missing"] == []
    assert set(json.loads((sim / "design.json").read_text())) == set(json.loads((multi / "design.json").read_text()))
    assert set(np.load(sim / "trajectory.npz").files) == set(np.load(multi / "trajectory.npz").files)
    processes = json.loads((multi / "processes.json").read_text())
    assert set(processes) == {"plant"} | {f"agent-{i}" for i in (range(1, 5) if "paper" in scenario else range(1, 9))}
    assert not any(pid_alive(pid) for pid in processes.values())


def test_agents_hosted_two_to_a_process_equal_simulate(tmp_path, paper_simulated):
    """``--agents-per-process 2``: two processes serve the four agents, each on one Zenoh session,
    and the trajectory is the in-process one; every agent still reports for itself."""
    out = tmp_path / "hosted"
    res = run_cli("run", "scenarios/paper.yaml", "--out", str(out), "--quiet", "--agents-per-process", "2")
    assert res.returncode == 0, res.stderr + res.stdout
    assert max_abs_diff(paper_simulated, out) <= 1e-9
    processes = json.loads((out / "processes.json").read_text())
    assert set(processes) == {"plant", "host-1", "host-2"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["launcher"]["hosts"] == {"host-1": ["1", "2"], "host-2": ["3", "4"]}
    assert summary["agent_reports_missing"] == []
    assert {name: entry["exit_code"] for name, entry in summary["agents"].items()} == dict.fromkeys("1234", 0)
    assert all(entry["solves"] > 0 and entry["rejected"] == {} for entry in summary["agents"].values())
    assert summary["fallbacks"] == 0 and summary["startup_s"] > 0 and "start-up" in res.stdout
    assert "agent 1: finished" in (out / "logs" / "host-1.log").read_text()
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
    assert "no release from the coordinator within 3 s" in text and "coordinator" in text
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


def _manual_run(procs, tmp_path, plant_net, agent_net, router=None, source="scenarios/paper.yaml"):
    out = tmp_path / "out"
    if router:
        procs.start("router", "--listen", router, log="router.log")
    plant = procs.start("plant", source, "--out", str(out), "--quiet", "--run-id", "t1",
                        "--startup-timeout", "60", *plant_net, log="plant.log")
    agents = [procs.start("agent", source, "--id", str(i), "--run-id", "t1",
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


def test_plant_and_agents_from_a_run_bundle(procs, tmp_path, paper_simulated):
    from dmpc.prepared.bundle import write_bundle
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    bundle = tmp_path / "run.json"
    write_bundle(prepare(load_scenario("scenarios/paper.yaml")), bundle)
    ep = f"tcp/127.0.0.1:{free_port()}"
    out = _manual_run(procs, tmp_path, ["--listen", ep], ["--connect", ep, "--listen", "tcp/127.0.0.1:0"],
                      source=str(bundle))
    assert max_abs_diff(paper_simulated, out) <= 1e-9
    assert json.loads((out / "run.json").read_text())["design"]["digest"] == \
        json.loads((paper_simulated / "design.json").read_text())["digest"]
    assert not (out / "scenario.yaml").exists()


def test_run_refuses_used_folder_with_exit_2(tmp_path, paper_simulated):
    res = run_cli("run", "scenarios/paper.yaml", "--out", str(paper_simulated), "--quiet")
    assert res.returncode == 2
    assert res.stderr.startswith("error:") and "already holds a run" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.skipif(os.cpu_count() is None, reason="needs cpu count")
def test_failed_child_stops_every_process(tmp_path):
    """With --fail-fast, a child that fails (here: an agent killed) stops the whole run; without it a
    crashed agent is a lost agent (test_e2e_hard_env)."""
    out = tmp_path / "run"
    proc = subprocess.Popen(DMPC + ["run", "scenarios/paper.yaml", "--out", str(out), "--quiet", "--fail-fast",
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


def test_agent_with_another_design_is_named_by_plant_and_agent(procs, tmp_path):
    """Agent 4 started with ``--set horizon=12`` against a plant of the scenario as it is: the
    plant fails at its start-up timeout naming agent 4 and both designs, and agent 4 says that
    its design differs from the coordinator's."""
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    scenario = ROOT / "scenarios" / "paper.yaml"
    plant_digest = prepare(load_scenario(scenario)).digest
    agent_digest = prepare(load_scenario(scenario, {"horizon": 12})).digest
    ep = f"tcp/127.0.0.1:{free_port()}"
    common = ["--run-id", "t7", "--connect", ep, "--listen", "tcp/127.0.0.1:0", "--startup-timeout", "90"]
    agents = [procs.start("agent", "scenarios/paper.yaml", "--id", str(i), *common,
                          *(["--set", "horizon=12"] if i == 4 else []), log=f"agent{i}.log") for i in range(1, 5)]
    plant = procs.start("plant", "scenarios/paper.yaml", "--out", str(tmp_path / "out"), "--quiet", "--run-id", "t7",
                        "--listen", ep, "--startup-timeout", "6", log="plant.log")
    plant.wait(timeout=90)
    for a in agents:
        a.wait(timeout=30)
    text = procs.log(plant)
    assert plant.returncode == 1, text
    assert "a design differs from this plant's" in text
    assert f"agent 4 uses design {agent_digest} (scenario 'paper', horizon 12)" in text
    assert f"this plant uses design {plant_digest} (scenario 'paper', horizon 10)" in text
    assert "agents 4 not ready within 6 s" in text and "Traceback" not in text
    assert agents[3].returncode == 1
    line = procs.log(agents[3])
    assert "agent 4: its design differs from the coordinator's" in line and agent_digest in line and plant_digest in line
    for a in agents[:3]:
        assert a.returncode == 1 and "its design differs" not in procs.log(a)
