"""End to end: ``dmpc run --plant external`` driven by a plant that is not dmpc.

The plant is examples/outside_plant.py (zenoh, msgpack and numpy only), whole or one sensor
process per subsystem, or one of its faulty variants (tests/helpers/bad_plant.py). Real
processes on loopback, multicast off, a free port per test.
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dmpc.bus import keys
from dmpc.bus.session import session_config
from dmpc.bus.zenoh_bus import ZenohBus
from tests.e2e_helpers import ROOT, Processes, free_port, max_abs_diff, step_lines, wait_for

EXAMPLE = ROOT / "examples" / "outside_plant.py"
SCENARIO = "scenarios/paper.yaml"

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


# ------------------------------------------------------------------------------------ helpers
class Run:
    """A ``dmpc run --plant external`` on a fixed port, and the plant processes started for it."""

    def __init__(self, procs: Processes, tmp: Path, *args: str, tls: bool = False) -> None:
        self.procs = procs
        self.out = tmp / "run"
        self.port = free_port()
        self.run_id = f"outside-{self.port}"
        self.endpoint = f"{'tls' if tls else 'tcp'}/127.0.0.1:{self.port}"
        self.run = procs.start("run", SCENARIO, "--plant", "external", "--port", str(self.port), "--run-id",
                               self.run_id, "--out", str(self.out), "--quiet", *args, log="run.log")

    def plant(self, *args: str, log: str = "plant.log", script: list[str] | None = None) -> subprocess.Popen:
        """The outside plant (or ``script``, e.g. a bad plant) connected to the run."""
        out = open(self.procs.tmp / log, "wb")
        proc = subprocess.Popen([*(script or [sys.executable, str(EXAMPLE)]), "--connect", self.endpoint,
                                 "--run-id", self.run_id, *args], cwd=ROOT, stdin=subprocess.DEVNULL, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        out.close()
        proc.log_path = self.procs.tmp / log
        self.procs.procs.append(proc)
        return proc

    def bad_plant(self, mode: str, *args: str, log: str = "bad-plant.log") -> subprocess.Popen:
        return self.plant(*args, log=log, script=[sys.executable, "-m", "tests.helpers.bad_plant", mode])

    def wait(self, timeout: float = 180) -> int:
        try:
            return self.run.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"dmpc run did not end within {timeout} s:\n{self.procs.log(self.run)[-3000:]}")

    def summary(self) -> dict:
        return json.loads((self.out / "summary.json").read_text())

    def log(self) -> str:
        return self.procs.log(self.run)


def ended(procs: Processes, proc: subprocess.Popen, timeout: float = 30) -> tuple[int, str]:
    try:
        code = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the plant did not exit within {timeout} s:\n{procs.log(proc)[-3000:]}")
    return code, procs.log(proc)


def last_line(text: str) -> str:
    return text.strip().splitlines()[-1]


def failed_with(run: Run, *words: str) -> dict:
    """The run stopped with exit code 1 and a failure that names ``words``; its summary."""
    code = run.wait()
    assert code == 1, run.log()[-3000:]
    summary = run.summary()
    failure = summary.get("failure") or ""
    for word in words:
        assert word in failure, (word, failure)
    assert summary["verdict"] == "failed" and "Traceback" not in run.log()
    return summary


# ------------------------------------------------------------------ the trajectory of simulate
def test_whole_state_plant_gives_the_trajectory_of_simulate(procs, tmp_path, paper_simulated):
    run = Run(procs, tmp_path)
    plant = run.plant()
    assert run.wait() == 0, run.log()[-3000:]
    code, text = ended(procs, plant)
    assert code == 0 and last_line(text) == "outside plant (plant): finished after 30 steps", text
    assert max_abs_diff(paper_simulated, run.out) <= 1e-9
    summary = run.summary()
    assert summary["verdict"] == "ok" and summary["rejected"] == {} and not summary.get("failure")


def test_one_sensor_process_per_subsystem_gives_the_trajectory_of_simulate(procs, tmp_path, paper_simulated):
    run = Run(procs, tmp_path)
    sensors = [run.plant("--sensor", name, log=f"sensor-{name}.log") for name in ("1", "2", "3", "4")]
    assert run.wait() == 0, run.log()[-3000:]
    for name, sensor in zip("1234", sensors):
        code, text = ended(procs, sensor)
        assert code == 0 and last_line(text) == f"outside plant (sensor-{name}): finished after 30 steps", text
    assert max_abs_diff(paper_simulated, run.out) <= 1e-9
    assert run.summary()["rejected"] == {}


def agents_ready(run: Run, names=("1", "2", "3", "4"), timeout: float = 60) -> None:
    """Return once every agent of ``run`` has said Ready on the run's bus (each repeats it every
    0.5 s until the first release), watched from a session of this process."""
    seen: set[str] = set()
    # the session retries until the coordinator listens
    bus = ZenohBus(session_config(connect=[run.endpoint]), open_timeout=timeout)
    try:
        bus.subscribe(keys.ready(run.run_id, "*"), lambda key, payload: seen.add(key.rsplit("/", 1)[-1]))
        assert bus.run(until=lambda: seen >= set(names), timeout=timeout), f"agents ready: {sorted(seen)}"
    finally:
        bus.close()


def test_a_late_plant_is_waited_for(procs, tmp_path, paper_simulated):
    run = Run(procs, tmp_path)
    agents_ready(run)  # the plant shows up only once the agents are ready and waiting for it
    assert run.run.poll() is None, run.log()
    plant = run.plant()
    assert run.wait() == 0, run.log()[-3000:]
    assert ended(procs, plant)[0] == 0
    assert max_abs_diff(paper_simulated, run.out) <= 1e-9


# ------------------------------------------------------------------------------ plant failures
def test_no_plant_fails_the_start_naming_the_plant(procs, tmp_path):
    run = Run(procs, tmp_path, "--startup-timeout", "6")
    summary = failed_with(run, "plant")
    assert summary["steps"] == 0


def test_a_plant_that_dies_mid_run_stops_the_run_after_the_plant_timeout(procs, tmp_path):
    run = Run(procs, tmp_path, "--plant-timeout", "3", "--set", "options.mode=realtime", "--set", "options.dt=0.2",
              "--steps", "40")
    plant = run.plant()
    assert wait_for(lambda: step_lines(run.out) >= 3, timeout=90), run.log()
    plant.send_signal(signal.SIGKILL)
    killed_at = time.monotonic()
    summary = failed_with(run, "plant", "no state for step")
    assert time.monotonic() - killed_at < 3 + 15
    assert 3 <= summary["steps"] < 40
    assert any(f["kind"] == "incomplete" for f in summary["failures"]), summary["failures"]


@pytest.mark.parametrize("mode, words", [
    ("shape", ["plant", "subsystem 2 has shape (3,), expected (2,)"]),
    ("nan", ["plant", "x[2]: non-finite values"]),
])
def test_a_wrong_state_is_dropped_and_the_run_stops_naming_it(procs, tmp_path, mode, words):
    run = Run(procs, tmp_path, "--plant-timeout", "1.5")
    plant = run.bad_plant(mode, "--from-step", "5")
    summary = failed_with(run, *words)
    assert 4 <= summary["steps"] <= 5  # x(5) never came
    assert summary["rejected"].get("plant", 0) > 0, summary["rejected"]
    code, text = ended(procs, plant)
    assert code == 1 and "the coordinator stopped the run" in text


def test_a_sensor_with_a_wrong_state_is_named(procs, tmp_path):
    run = Run(procs, tmp_path, "--plant-timeout", "1.5")
    good = [run.plant("--sensor", name, log=f"sensor-{name}.log") for name in ("1", "3", "4")]
    run.bad_plant("shape", "--sensor", "2", "--from-step", "2")
    summary = failed_with(run, "sensor-2", "subsystems 2", "shape (3,)")
    assert summary["rejected"].get("sensor-2", 0) > 0 and set(summary["rejected"]) == {"sensor-2"}
    for sensor in good:
        assert ended(procs, sensor)[0] == 1


def test_a_plant_of_another_protocol_version_is_named_with_both_versions(procs, tmp_path):
    run = Run(procs, tmp_path, "--startup-timeout", "6")
    run.bad_plant("version")
    summary = failed_with(run, "plant", "protocol version 2; this process speaks protocol version 3")
    assert summary["steps"] == 0


# ------------------------------------------------------------------------ TLS and access control
def test_with_tls_the_plant_role_publishes_states_and_nothing_else(procs, tmp_path, paper_simulated):
    """A plant holding the plant's valid certificate also publishes releases, plans of agent 1,
    ready messages and Stop at every step: the access control drops all of them, and the run
    follows the clean trajectory."""
    run = Run(procs, tmp_path, "--secure", tls=True)
    tls = run.out / "tls"
    assert wait_for(lambda: (tls / "plant.key").exists() and (tls / "acl.json").exists(), timeout=60), run.log()
    rogue = run.bad_plant("rogue", "--tls", str(tls))
    assert run.wait() == 0, run.log()[-3000:]
    code, text = ended(procs, rogue)
    assert code == 0, text
    forged = int(text.rsplit("ROGUE SENT ", 1)[1].split()[0])
    assert forged >= 4 * 30, text  # four forgeries at each of the 30 steps
    assert max_abs_diff(paper_simulated, run.out) <= 1e-9
    summary = run.summary()
    assert summary["verdict"] == "ok" and summary["security"]["access_control"] is True
    assert summary["rejected"] == {}  # denied messages never reach the coordinator
    assert all(agent["rejected"] == {} for agent in summary["agents"].values()), summary["agents"]
