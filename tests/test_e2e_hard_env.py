"""Hard environments, with real processes: full and read-only disks, signals while connecting,
port clashes between concurrent runs, crashed agents restarted or lost, a killed launcher."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from tests.e2e_helpers import DMPC, ROOT, pid_alive, run_cli, step_lines, wait_for

pytestmark = pytest.mark.e2e

REALTIME = ["--set", "options.mode=realtime", "--set", "options.dt=0.05"]


def _tmpfs(folder: Path, options: str):
    """Mount a tmpfs with ``options`` on ``folder`` (created); needs root. Yields it, then unmounts."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (CI runs as root)")
    folder.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], check=True)
    yield folder
    subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MiB disk."""
    yield from _tmpfs(tmp_path / "disk", "size=1m")


@pytest.fixture
def read_only(tmp_path):
    """An empty read-only folder (for root, permissions do not apply: a read-only mount does)."""
    yield from _tmpfs(tmp_path / "ro", "ro,size=64k")


def complete_lines(path: Path) -> list[dict]:
    text = path.read_text()
    assert text == "" or text.endswith("\n"), "the step log ends with a partial line"
    return [json.loads(line) for line in text.splitlines()]


# --------------------------------------------------------------------------- the disk
def test_a_full_disk_stops_the_run_with_one_clear_line_and_keeps_the_steps(small_disk):
    out = small_disk / "run"
    res = run_cli("run", "scenarios/chain.yaml", "--set", "family.M=8", "--steps", "3000", "--out", str(out),
                  "--quiet", timeout=180)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "No space left on device" in res.stderr, res.stderr
    assert f"cannot write {out}" in res.stderr
    assert "Traceback" not in res.stderr
    steps = complete_lines(out / "steps.jsonl")
    assert 0 < len(steps) < 3000
    assert [s["k"] for s in steps] == list(range(len(steps)))


def test_a_full_disk_in_process_exits_1_naming_the_file(small_disk):
    out = small_disk / "sim"
    res = run_cli("simulate", "scenarios/chain.yaml", "--set", "family.M=8", "--steps", "3000", "--out", str(out),
                  "--quiet", timeout=180)
    assert res.returncode == 1, res.stdout + res.stderr
    [line] = res.stderr.strip().splitlines()
    assert line.startswith(f"error: cannot write {out}/") and "No space left on device" in line
    assert "completed steps are kept" in line
    assert len(complete_lines(out / "steps.jsonl")) > 0


@pytest.mark.parametrize("command", ["run", "simulate"])
def test_a_read_only_output_folder_is_exit_2_in_one_line(read_only, command):
    res = run_cli(command, "scenarios/paper.yaml", "--out", str(read_only), "--quiet")
    assert res.returncode == 2, res.stderr
    [line] = res.stderr.strip().splitlines()
    assert line.startswith(f"error: cannot write {read_only}/") and "Read-only file system" in line, line


# --------------------------------------------------------------------------- signals
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_an_agent_that_cannot_reach_its_plant_ends_at_once_on_a_signal(procs, sig):
    # port 1 on loopback refuses every connection: the agent keeps trying until its start-up timeout
    agent = procs.start("agent", "scenarios/paper.yaml", "--id", "1", "--connect", "tcp/127.0.0.1:1",
                        "--startup-timeout", "20")
    import psutil

    def connecting() -> bool:  # its session is open for listening: it is trying the connect endpoint
        try:
            return any(c.status == psutil.CONN_LISTEN for c in psutil.Process(agent.pid).net_connections("tcp"))
        except psutil.Error:
            return False

    assert wait_for(connecting, 60)
    time.sleep(1.0)
    assert agent.poll() is None
    sent = time.monotonic()
    os.kill(agent.pid, sig)
    agent.wait(timeout=10)
    assert time.monotonic() - sent < 2.0
    assert agent.returncode == 130
    assert "interrupted" in procs.log(agent)


# --------------------------------------------------------------------------- ports
def test_concurrent_runs_do_not_clash_on_ports(tmp_path):
    runs = int(os.environ.get("DMPC_PORT_RUNS", "6"))
    outs = [tmp_path / f"r{i}" for i in range(runs)]
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda out: run_cli("run", "scenarios/paper.yaml", "--out", str(out), "--quiet",
                                                    "--steps", "10"), outs))
    failed = [(i, r.returncode, r.stderr[-500:]) for i, r in enumerate(results) if r.returncode != 0]
    assert not failed
    assert not any("Address already in use" in r.stderr for r in results)


def test_a_port_taken_before_the_plant_binds_it_is_retried(tmp_path, monkeypatch):
    import socket

    from dmpc.runtime import launcher
    from dmpc.scenario import load_scenario
    from dmpc.setup import prepare

    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    taken = blocker.getsockname()[1]
    ports = iter([taken])
    real = launcher.free_port
    monkeypatch.setattr(launcher, "free_port", lambda: next(ports, None) or real())
    try:
        prepared = prepare(load_scenario(ROOT / "scenarios/paper.yaml", {"steps": 5}))
        result = launcher.launch(prepared, tmp_path / "run", "clash", startup_timeout=20, show_progress=False)
    finally:
        blocker.close()
    assert result.code == 0, result.message
    assert result.summary["steps"] == 5
    assert "Address already in use" in (tmp_path / "run" / "logs" / "plant.log").read_text()


def test_a_plant_that_cannot_listen_exits_with_the_address_in_use_code(tmp_path):
    import socket

    from dmpc.terminal.exit_codes import EXIT_ADDRESS_IN_USE, EXIT_FAILED

    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        taken = blocker.getsockname()[1]
        res = run_cli("plant", "scenarios/paper.yaml", "--out", str(tmp_path / "run"), "--quiet",
                      "--listen", f"tcp/127.0.0.1:{taken}", "--startup-timeout", "3")
    assert res.returncode == EXIT_ADDRESS_IN_USE != EXIT_FAILED, res.stderr
    [line] = res.stderr.strip().splitlines()
    assert line.startswith("error: ") and "Address already in use" in line and f"127.0.0.1:{taken}" in line


def test_free_ports_are_drawn_below_the_ephemeral_range():
    from dmpc.runtime.launcher import _ephemeral_range, free_port

    low, high = _ephemeral_range()
    assert all(not low <= free_port() <= high for _ in range(20))


# --------------------------------------------------------------------------- crashed agents
def _kill_at(out: Path, plan: list[tuple[str, int]]) -> None:
    for role, at in plan:
        assert wait_for(lambda at=at: step_lines(out) >= at, 60), f"step {at} never came"
        os.kill(json.loads((out / "processes.json").read_text())[role], signal.SIGKILL)


def _start_run(out: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(DMPC + ["run", "scenarios/paper.yaml", "--out", str(out), "--quiet", *REALTIME, *args],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _no_orphans(out: Path) -> None:
    pids = json.loads((out / "processes.json").read_text()).values()
    # a hang guard, not a measure (tests/test_e2e_runtime.py times the exits): a busy machine may take
    # seconds to let a process close its session
    assert wait_for(lambda: not any(pid_alive(p) for p in pids), 30), "a child outlived the run"


def test_restarted_agents_rejoin_and_fall_back_only_in_their_gaps(tmp_path):
    out = tmp_path / "run"
    # a deadline far above a plan's time, however loaded the machine: the killed agents are found
    # lost by liveliness, and an agent that is only slow must not fall back
    proc = _start_run(out, "--steps", "70", "--restart", "3", "--set", "options.deadline=1.0")
    try:
        _kill_at(out, [("agent-2", 12), ("agent-3", 35)])
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, stdout + stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 70 and summary["verdict"] == "ok"
    assert [w["kind"] for w in summary["warnings"]] == ["fallbacks"]
    assert summary["launcher"]["restarts"] == {"agent-2": 1, "agent-3": 1}
    assert summary["launcher"]["lost"] == []
    notes = " ".join(summary["notes"])
    assert "agent 2 lost" in notes and "agent 2 back" in notes and "agent 3 lost" in notes and "agent 3 back" in notes
    by_agent: dict[str, list[int]] = {}
    for k, name in summary["fallback_steps"]:
        by_agent.setdefault(name, []).append(k)
    assert set(by_agent) == {"2", "3"}
    for name, steps in by_agent.items():  # one gap each: from its loss to its return
        assert steps == list(range(steps[0], steps[-1] + 1)), (name, steps)
    assert by_agent["2"][0] >= 12 and by_agent["3"][0] >= 35 and by_agent["2"][-1] < by_agent["3"][0]
    x = np.load(out / "trajectory.npz")["x"]
    assert np.max(np.abs(x[-1])) < 1e-3
    assert summary["agent_reports_missing"] == [] and set(summary["agents"]) == {"1", "2", "3", "4"}
    _no_orphans(out)


def _run_killing(out, role: str, *args: str):
    """A 40-step ``dmpc run`` whose process ``role`` is SIGKILLed at step 10: (process, summary, stderr)."""
    proc = _start_run(out, "--steps", "40", *args)
    try:
        _kill_at(out, [(role, 10)])
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc, json.loads((out / "summary.json").read_text()), stderr


def test_without_restart_a_crashed_agent_is_lost_and_the_run_goes_on(tmp_path):
    out = tmp_path / "run"
    proc, summary, stderr = _run_killing(out, "agent-4")
    assert summary["steps"] == 40, stderr
    assert summary["launcher"]["lost"] == ["agent-4"]
    assert {name for _, name in summary["fallback_steps"]} == {"4"}
    lost_from = summary["fallback_steps"][0][0]
    assert lost_from >= 10 and [k for k, _ in summary["fallback_steps"]] == list(range(lost_from, 40))
    assert "fallbacks" in [w["kind"] for w in summary["warnings"]]
    assert summary["agent_reports_missing"] == ["4"]
    assert proc.returncode == (0 if summary["verdict"] == "ok" else 3)
    _no_orphans(out)


def test_a_killed_host_process_is_the_loss_of_its_agents_and_the_run_goes_on(tmp_path):
    """SIGKILL the process that serves agents 3 and 4 (``--agents-per-process 2``): the plant sees
    both liveliness tokens go and falls back for both from then on, as for lost agents; the other
    host's agents never fall back."""
    out = tmp_path / "run"
    proc, summary, stderr = _run_killing(out, "host-2", "--agents-per-process", "2")
    assert summary["steps"] == 40, stderr
    assert summary["launcher"]["lost"] == ["host-2"] and summary["launcher"]["crashes"] == {"host-2": [-9]}
    by_agent: dict[str, list[int]] = {}
    for k, name in summary["fallback_steps"]:
        by_agent.setdefault(name, []).append(k)
    assert set(by_agent) == {"3", "4"}
    for steps in by_agent.values():  # from the loss to the end
        assert steps[0] >= 10 and steps == list(range(steps[0], 40)), steps
    notes = " ".join(summary["notes"])
    assert "agent 3 lost" in notes and "agent 4 lost" in notes
    assert summary["agent_reports_missing"] == ["3", "4"] and set(summary["agents"]) == {"1", "2"}
    assert proc.returncode == (0 if summary["verdict"] == "ok" else 3)
    _no_orphans(out)


def test_fail_fast_stops_the_run_when_an_agent_crashes(tmp_path):
    out = tmp_path / "run"
    proc = _start_run(out, "--steps", "200", "--fail-fast")
    try:
        _kill_at(out, [("agent-1", 5)])
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 1
    assert "agent-1 exited with code -9 (--fail-fast)" in stderr
    assert step_lines(out) < 200
    _no_orphans(out)


def test_a_killed_launcher_leaves_a_summary_with_the_agents_reports(tmp_path):
    out = tmp_path / "run"
    proc = _start_run(out, "--steps", "300")
    try:
        assert wait_for(lambda: step_lines(out) >= 5, 60)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        assert wait_for(lambda: (out / "summary.json").exists() and "agent_reports_missing" in json.loads(
            (out / "summary.json").read_text()), 60)  # a hang guard: the processes see the launcher gone
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["aborted"] == "interrupted"
    assert set(summary["agents"]) | set(summary["agent_reports_missing"]) == {"1", "2", "3", "4"}
    assert len(summary["agents"]) >= 3
    _no_orphans(out)
