"""A setpoint schedule run as processes over Zenoh gives the trajectory of ``dmpc simulate``: the
targets travel in the releases and every agent solves around them (docs/algorithm.md, "Setpoints")."""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.e2e_helpers import max_abs_diff, run_cli

pytestmark = pytest.mark.e2e

SCHEDULE = ["--set", "steps=80", "--set",
            'setpoints=[{at: 0, subsystem: "1", x: [1.0, null]}, {at: 40, subsystem: "1", x: [-0.5, null]}]']


def test_a_schedule_run_as_processes_equals_simulate(tmp_path):
    sim, multi = tmp_path / "sim", tmp_path / "multi"
    res = run_cli("simulate", "scenarios/paper.yaml", "--out", str(sim), "--quiet", *SCHEDULE)
    assert res.returncode == 0, res.stderr + res.stdout
    res = run_cli("run", "scenarios/paper.yaml", "--out", str(multi), "--quiet", *SCHEDULE, timeout=180)
    assert res.returncode == 0, res.stderr + res.stdout
    keys = ("x", "u", "alpha", "beta", "J", "target", "target_u", "reference", "reference_u", "governor")
    assert max_abs_diff(sim, multi, keys) <= 1e-9
    summary = json.loads((multi / "summary.json").read_text())
    assert summary["verdict"] == "ok" and summary["fallbacks"] == 0 and summary["feasible"]
    x = np.load(multi / "trajectory.npz")["x"]
    assert abs(x[40, 0] - 1.0) < 1e-4 and abs(x[80, 0] + 0.5) < 1e-4
    assert np.linalg.norm(x[80] - x[79]) < 1e-6
    line = json.loads((multi / "steps.jsonl").read_text().splitlines()[45])
    assert line["setpoint"][0] == -0.5 and line["governor"] == 1.0
