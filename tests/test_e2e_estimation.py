"""End to end, offset-free estimation (issue 31; docs/algorithm.md, "Offset-free tracking"): the
nonlinear four-tank with h1 and h2 measured only and an observer per subsystem
(scenarios/fourtank-levels.yaml, its first 300 steps) as real processes over Zenoh on loopback
(``dmpc run``) gives ``dmpc simulate``'s run bit for bit: the plant's states, the inputs, what the
controllers saw of the plant (y, x^, d^, the innovation), the terminal boxes, the targets and every
recorded plan. The coordinator runs the observers and releases x^ to every agent, so the agents'
processes must not change a bit of it.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.e2e_helpers import pid_alive, run_cli

pytestmark = pytest.mark.e2e

SCENARIO = "scenarios/fourtank-levels.yaml"
STEPS = 300
NAMES = ("a", "b")
KEYS = ("x", "u", "y", "x_hat", "d_hat", "innovation", "setpoint_y", "alpha", "beta", "J", "S", "J_agents", "target", "target_u",
        "reference", "reference_u", "governor") + tuple(f"plan_{part}_{name}" for name in NAMES for part in ("z", "v"))
"""Every array compared, bit for bit."""


def differing(a, b, keys) -> list[str]:
    """The ``keys`` whose arrays in the run folders ``a`` and ``b`` differ in shape or in any bit (NaN
    equal to NaN where its bits are)."""
    A, B = np.load(a / "trajectory.npz"), np.load(b / "trajectory.npz")
    return [k for k in keys if A[k].shape != B[k].shape or A[k].tobytes() != B[k].tobytes()]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("estimation-sim") / "sim"
    res = run_cli("simulate", SCENARIO, "--set", f"steps={STEPS}", "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "tv-box-coop" and summary["verdict"] == "ok" and summary["fallbacks"] == 0
    return out


def test_run_over_zenoh_equals_simulate_bit_for_bit(tmp_path, simulated):
    out = tmp_path / "run"
    res = run_cli("run", SCENARIO, "--set", f"steps={STEPS}", "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr + res.stdout
    arrays = np.load(out / "trajectory.npz")
    assert set(KEYS) <= set(arrays.files)
    assert arrays["x_hat"].shape == (STEPS, 4) and arrays["y"].shape == (STEPS, 2) and arrays["d_hat"].shape == (STEPS, 2)
    assert np.abs(arrays["d_hat"][-1]).max() > 0  # the observer did work: the model is not the plant
    assert differing(simulated, out, KEYS) == []
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runtime"] == "multi-process" and summary["method"] == "tv-box-coop"
    assert summary["verdict"] == "ok" and summary["fallbacks"] == 0 and summary["qp_failed"] == 0
    assert summary["steps"] == STEPS and summary["agent_reports_missing"] == []
    assert {name: entry["exit_code"] for name, entry in summary["agents"].items()} == dict.fromkeys(NAMES, 0)
    started = json.loads((out / "processes.json").read_text())
    assert set(started) == {"plant", "agent-a", "agent-b"}
    assert not any(pid_alive(pid) for pid in started.values())
