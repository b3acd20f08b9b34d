"""End to end: the coordinator and dmpc's simulated plant as processes of their own.

``dmpc plant --coordinator external`` (the whole state, or ``--sensor I`` per subsystem) serves a
``dmpc run --plant external`` or a ``dmpc coordinator --plant external`` started by hand, and
gives the trajectory of ``dmpc simulate``; ``dmpc plant`` and ``dmpc coordinator`` started by
hand exit 3 when the run completes with a failed verdict, as ``dmpc run`` does (README, "Outcomes
and exit codes"). Real processes on loopback, multicast off, a free port per test.
"""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from tests.e2e_helpers import Processes, free_port, max_abs_diff, wait_for

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

SCENARIO = "scenarios/paper.yaml"
# a start that the input bound of subsystem 1 cannot steer: the run completes, its verdict fails
FAILING = ["--set", "subsystems[0].input={lower: [-0.01], upper: [0.01]}", "--set", "terminal.beta0=auto",
           "--set", "design.check_start=false", "--set", "steps=12"]


def ended(procs: Processes, proc: subprocess.Popen, timeout: float, what: str) -> tuple[int, str]:
    """The exit code and log of ``proc`` once it has exited."""
    try:
        code = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{what} did not exit within {timeout} s:\n{procs.log(proc)[-3000:]}")
    return code, procs.log(proc)


def last_line(text: str) -> str:
    return text.strip().splitlines()[-1]


def summary_of(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def start_plant_alone(procs: Processes, endpoint: str, run_id: str, *sensors: str, tls: Path | None = None,
                      extra: tuple[str, ...] = ()) -> subprocess.Popen:
    """``dmpc plant --coordinator external``: the whole state, or the sensors of ``sensors``."""
    flags = [arg for name in sensors for arg in ("--sensor", name)]
    log = f"sensor-{'-'.join(sensors)}.log" if sensors else "plant.log"
    return procs.start("plant", SCENARIO, "--coordinator", "external", *flags, "--connect", endpoint,
                       "--run-id", run_id, "--startup-timeout", "90", *(["--tls", str(tls)] if tls else []),
                       *extra, log=log)


# ---------------------------------------------------------- the plant alone serves dmpc run
@pytest.mark.parametrize("sensors", [(), (("1",), ("2",), ("3", "4"))], ids=["whole-state", "sensors"])
def test_the_plant_alone_gives_the_trajectory_of_simulate(procs, tmp_path, paper_simulated, sensors):
    """``dmpc run --plant external`` served by ``dmpc plant --coordinator external``: one process
    for the whole state, or sensors 1 and 2 in a process each and 3 and 4 in a third."""
    port = free_port()
    run_id, out = f"alone-{port}", tmp_path / "run"
    run = procs.start("run", SCENARIO, "--plant", "external", "--port", str(port), "--run-id", run_id,
                      "--out", str(out), "--quiet", log="run.log")
    endpoint = f"tcp/127.0.0.1:{port}"
    plants = [start_plant_alone(procs, endpoint, run_id, *group) for group in sensors] if sensors \
        else [start_plant_alone(procs, endpoint, run_id)]
    code, log = ended(procs, run, 240, "dmpc run")
    assert code == 0, log[-3000:]
    for group, plant in zip(sensors or [()], plants):
        code, text = ended(procs, plant, 30, "the plant")
        who = f"sensors {', '.join(group)}" if group else "plant"
        assert code == 0 and last_line(text) == f"{who}: finished after 30 steps", text
    assert max_abs_diff(paper_simulated, out) <= 1e-9
    summary = summary_of(out)
    assert summary["verdict"] == "ok" and summary["plant"] == {"model": "outside"}
    assert summary["rejected"] == {} and not summary.get("failure")


def test_sensors_alone_under_tls_and_access_control_give_the_trajectory_of_simulate(procs, tmp_path,
                                                                                    paper_simulated):
    """``dmpc run --secure --plant external`` served by one ``dmpc plant --coordinator external
    --sensor I --tls`` per subsystem: the rights of the sensor certificates are all a sensor needs."""
    port = free_port()
    run_id, out = f"secure-{port}", tmp_path / "run"
    run = procs.start("run", SCENARIO, "--secure", "--plant", "external", "--port", str(port), "--run-id", run_id,
                      "--out", str(out), "--quiet", log="run.log")
    tls = out / "tls"
    assert wait_for(lambda: all((tls / f"sensor-{n}.key").exists() for n in "1234") and (tls / "acl.json").exists(),
                    timeout=90), procs.log(run)
    sensors = [start_plant_alone(procs, f"tls/127.0.0.1:{port}", run_id, name, tls=tls) for name in "1234"]
    code, log = ended(procs, run, 240, "dmpc run")
    assert code == 0, log[-3000:]
    for name, sensor in zip("1234", sensors):
        code, text = ended(procs, sensor, 30, f"sensor {name}")
        assert code == 0 and last_line(text) == f"sensors {name}: finished after 30 steps", text
    assert max_abs_diff(paper_simulated, out) <= 1e-9
    summary = summary_of(out)
    assert summary["verdict"] == "ok" and summary["rejected"] == {}
    assert summary["security"]["access_control"] is True


# ------------------------------------------------- started by hand: a failed verdict exits 3
def by_hand(procs: Processes, tmp_path: Path, coordinator: list[str], plant_alone: bool) -> dict:
    """The coordinator's process (``coordinator``: its command and flags), the plant alone if
    ``plant_alone``, and the four agents in one ``dmpc agent`` process, all with ``FAILING``;
    their exit codes and last lines, and the run's summary."""
    port = free_port()
    run_id, out, endpoint = f"hand-{port}", tmp_path / "run", f"tcp/127.0.0.1:{port}"
    common = ["--run-id", run_id, "--startup-timeout", "90", *FAILING]
    head = procs.start(*coordinator, SCENARIO, "--out", str(out), "--listen", endpoint, "--quiet", *common,
                       log="coordinator.log")
    plant = start_plant_alone(procs, endpoint, run_id, extra=tuple(FAILING)) if plant_alone else None
    agents = procs.start("agent", SCENARIO, *[a for n in "1234" for a in ("--id", n)], "--connect", endpoint,
                         *common, log="agents.log")
    ends = {"coordinator": ended(procs, head, 240, coordinator[0])}
    ends["agents"] = ended(procs, agents, 30, "the agents")
    if plant is not None:
        ends["plant"] = ended(procs, plant, 30, "the plant")
    return {"ends": {who: (code, last_line(text)) for who, (code, text) in ends.items()},
            "logs": {who: text for who, (_, text) in ends.items()}, "summary": summary_of(out)}


@pytest.mark.parametrize("coordinator, plant_alone, who", [
    (["plant"], False, "plant"),
    (["coordinator", "--plant", "external"], True, "coordinator"),
], ids=["dmpc-plant", "dmpc-coordinator"])
def test_started_by_hand_a_completed_run_with_a_failed_verdict_exits_3(procs, tmp_path, coordinator, plant_alone,
                                                                       who):
    """``dmpc plant`` (the coordinator and the simulated plant), or ``dmpc coordinator --plant
    external`` beside ``dmpc plant --coordinator external``, with the agents: the 12 steps are
    done, the verdict fails, the coordinator's process exits 3 naming the failures. The agents
    and the plant alone did their part: they exit 0 (the verdict is the coordinator's)."""
    run = by_hand(procs, tmp_path, coordinator, plant_alone)
    summary = run["summary"]
    assert summary["verdict"] == "failed" and summary["steps"] == 12 and not summary.get("failure"), summary
    kinds = ", ".join(dict.fromkeys(f["kind"] for f in summary["failures"]))
    assert run["ends"]["coordinator"] == (3, f"error: {who}: finished 12 steps; verdict failed ({kinds})"), \
        run["logs"]["coordinator"][-3000:]
    assert "Traceback" not in run["logs"]["coordinator"]
    assert run["ends"]["agents"][0] == 0, run["logs"]["agents"][-3000:]
    if plant_alone:
        assert run["ends"]["plant"] == (0, "plant: finished after 12 steps"), run["logs"]["plant"][-3000:]
