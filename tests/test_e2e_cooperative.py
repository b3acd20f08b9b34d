"""End to end, ``tv-box-coop``: the four-tank benchmark as real processes over Zenoh on loopback
(``dmpc run``: the launcher picks a free port) gives ``dmpc simulate``'s trajectory to 1e-9: states,
inputs, costs, terminal boxes, targets and every recorded plan, one process per agent and with
the agents hosted two to a process. The whole scenario runs (600 steps, about 4 s per
run here), so both setpoint changes and the reference governor's moves are in it.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.e2e_helpers import max_abs_diff, pid_alive, run_cli

pytestmark = pytest.mark.e2e

SCENARIO = "scenarios/fourtank.yaml"
NAMES = ("a", "b")
KEYS = ("x", "u", "alpha", "beta", "J", "S", "J_agents", "target", "target_u", "reference", "reference_u",
        "governor") + tuple(f"plan_{part}_{name}" for name in NAMES for part in ("z", "v"))
"""Every array compared: the plans are the last cooperative iterate of each step."""


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("coop-sim") / "sim"
    res = run_cli("simulate", SCENARIO, "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "tv-box-coop" and summary["verdict"] == "ok" and summary["fallbacks"] == 0
    return out


@pytest.mark.parametrize("hosting, processes", [([], {"plant", "agent-a", "agent-b"}),
                                                (["--agents-per-process", "2"], {"plant", "host-1"})],
                         ids=["one-per-agent", "hosted-two"])
def test_run_equals_simulate(tmp_path, simulated, hosting, processes):
    out = tmp_path / "run"
    res = run_cli("run", SCENARIO, "--out", str(out), "--quiet", *hosting)
    assert res.returncode == 0, res.stderr + res.stdout
    assert set(KEYS) <= set(np.load(out / "trajectory.npz").files)
    assert max_abs_diff(simulated, out, KEYS) <= 1e-9
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runtime"] == "multi-process" and summary["method"] == "tv-box-coop"
    assert summary["verdict"] == "ok" and summary["fallbacks"] == 0 and summary["qp_failed"] == 0
    assert summary["steps"] == 600 and summary["agent_reports_missing"] == []
    if hosting:
        assert summary["launcher"]["hosts"] == {"host-1": list(NAMES)}
    assert {name: entry["exit_code"] for name, entry in summary["agents"].items()} == dict.fromkeys(NAMES, 0)
    started = json.loads((out / "processes.json").read_text())
    assert set(started) == processes
    assert not any(pid_alive(pid) for pid in started.values())
