"""End to end: the event trigger over Zenoh (``options.trigger: event``) gives the run of ``dmpc simulate``.

The paper's example with two agents to a process: the kept plans are rebuilt by the coordinator
and by the neighbours from the kept notices alone, so the trajectory, the plans and which agent
kept at which step equal the in-process run, and the messages counted are the ones sent.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.e2e_helpers import max_abs_diff, run_cli

pytestmark = pytest.mark.e2e

EVENT = ("--set", "options.trigger=event", "--set", "steps=40")


def test_event_run_equals_simulate_and_sends_kept_notices(tmp_path):
    sim, multi = tmp_path / "sim", tmp_path / "multi"
    res = run_cli("simulate", "scenarios/paper.yaml", "--out", str(sim), "--quiet", *EVENT)
    assert res.returncode == 0, res.stderr
    res = run_cli("run", "scenarios/paper.yaml", "--out", str(multi), "--quiet", "--agents-per-process", "2", *EVENT)
    assert res.returncode == 0, res.stderr + res.stdout
    assert max_abs_diff(sim, multi) <= 1e-9
    A, B = np.load(sim / "trajectory.npz"), np.load(multi / "trajectory.npz")
    assert np.array_equal(A["kept"], B["kept"])
    for name in ("1", "2", "3", "4"):
        assert np.nanmax(np.abs(A[f"plan_z_{name}"] - B[f"plan_z_{name}"])) <= 1e-9
    s_sim, s_multi = (json.loads((f / "summary.json").read_text()) for f in (sim, multi))
    assert s_multi["verdict"] == "ok" and s_multi["fallbacks"] == 0
    assert s_multi["keeps"] == s_sim["keeps"] > 0 and s_multi["solves"] == s_sim["solves"]
    messages = s_multi["messages"]
    # every plan kept (the step records) is one kept notice that reached the coordinator
    assert messages["kept_notices"] == s_multi["keeps"]
