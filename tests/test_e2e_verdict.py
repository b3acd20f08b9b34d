"""``dmpc run`` and ``dmpc simulate`` agree on the verdict, and a failed verdict exits 3 (real processes)."""
from __future__ import annotations

import json

import pytest

from tests.e2e_helpers import max_abs_diff, run_cli

pytestmark = pytest.mark.e2e

TINY_INPUT = ["--set", "subsystems[0].input={lower: [-0.01], upper: [0.01]}", "--set", "terminal.beta0=auto",
              "--set", "design.check_start=false", "--steps", "12"]


def test_run_and_simulate_agree_on_a_failed_verdict(tmp_path):
    sim = run_cli("simulate", "scenarios/paper.yaml", "--out", str(tmp_path / "sim"), "--quiet", *TINY_INPUT)
    multi = run_cli("run", "scenarios/paper.yaml", "--out", str(tmp_path / "run"), "--quiet", *TINY_INPUT)
    assert sim.returncode == 3, sim.stderr
    assert multi.returncode == 3, multi.stdout + multi.stderr
    a = json.loads((tmp_path / "sim" / "summary.json").read_text())
    b = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert a["verdict"] == b["verdict"] == "failed"
    assert [(f["kind"], f["subsystem"], f["steps"]) for f in a["failures"]] == \
           [(f["kind"], f["subsystem"], f["steps"]) for f in b["failures"]]
    assert max_abs_diff(tmp_path / "sim", tmp_path / "run") < 1e-9
    assert multi.stdout.splitlines()[0].startswith("verdict: FAILED (")
    assert "error:" not in multi.stderr  # a completed run with a failed verdict is not a process failure
