"""The run's verdict: each failure and warning kind, on screen, in summary.json and in the exit code."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dmpc.agents.controller import AgentController
from dmpc.core.mpc_qp import QPStatus
from dmpc.core.system import CoupledSystem, LinearSet, Subsystem
from dmpc.records.verdict import DIVERGENCE_FACTOR, RunLimits, judge, state_bound_excess
from tests.helpers.cli import call

TWO_CARTS = """
name: {name}
subsystems:
  - {{name: a, A: [[1.0, 0.2], [0.0, 1.0]], B: [[0.02], [0.2]], Q: [[1, 0], [0, 0.1]], R: [[0.1]],
     input: {{lower: [{umin}], upper: [{umax}]}}, state: {{lower: [-5, -3], upper: [5, 3]}}, x0: {xa}}}
  - {{name: b, A: [[1.0, 0.2], [0.0, 1.0]], B: [[0.02], [0.2]], Q: [[1, 0], [0, 0.1]], R: [[0.1]],
     input: {{lower: [{umin}], upper: [{umax}]}}, state: {{lower: [-5, -3], upper: [5, 3]}}, x0: {xb}}}
couplings:
  - {{target: a, source: b, A: [[0.005, 0.0], [0.05, 0.0]]}}
  - {{target: b, source: a, A: [[0.005, 0.0], [0.05, 0.0]]}}
horizon: {horizon}
steps: {steps}
design: {{gains: lmi, check_start: {check}}}
"""


def scenario(tmp_path: Path, name: str = "carts2", umin: float = -1, umax: float = 1, xa=(2.0, 0.0),
             xb=(-1.0, 0.5), horizon="auto", steps: int = 60, check: bool = True) -> str:
    path = tmp_path / f"{name}.yaml"
    path.write_text(TWO_CARTS.format(name=name, umin=umin, umax=umax, xa=list(xa), xb=list(xb), horizon=horizon,
                                     steps=steps, check=str(check).lower()))
    return str(path)


def simulate(monkeypatch, capsys, tmp_path: Path, *args: str) -> tuple[int, str, str, dict]:
    out = tmp_path / f"run{len(list(tmp_path.glob('run*')))}"
    code, stdout, stderr = call(monkeypatch, capsys, "simulate", *args, "--out", str(out), "--quiet")
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    return code, stdout, stderr, summary


def kinds(findings: list[dict]) -> set[str]:
    return {f["kind"] for f in findings}


# --------------------------------------------------------------------------- runs that are ok
def test_paper_is_ok_with_exit_0(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/paper.yaml")
    assert code == 0
    assert summary["verdict"] == "ok" and summary["failures"] == [] and summary["warnings"] == []
    assert out.splitlines()[0] == "verdict: ok"


def test_chain_is_ok_with_exit_0(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/chain.yaml", "--set", "family.M=6")
    assert code == 0 and summary["verdict"] == "ok", summary["failures"]


def test_carts_with_the_defaults_choose_a_horizon_and_are_ok(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/carts.yaml")
    assert code == 0 and summary["verdict"] == "ok", out
    design = json.loads((tmp_path / "run0" / "design.json").read_text())
    start = design["start"]
    assert start["horizon"] == "auto" and design["horizon"] == start["chosen"] == summary["horizon"]
    assert start["smallest_feasible"] >= start["smallest_centrally_feasible"] >= 1
    assert start["chosen"] - start["smallest_feasible"] == max(2, int(np.ceil(0.2 * start["smallest_feasible"])))
    assert design["beta0"] == pytest.approx(0.9 * design["sigma0"])
    assert "(auto)" in out


def test_carts_at_a_short_horizon_name_the_horizon_the_distributed_step_needs(monkeypatch, capsys, tmp_path):
    design = json.loads(call(monkeypatch, capsys, "design", "scenarios/carts.yaml", "--json")[1])
    start = design["start"]
    assert start["smallest_feasible"] > start["smallest_centrally_feasible"]  # the case where the two differ
    code, _, err = call(monkeypatch, capsys, "simulate", "scenarios/carts.yaml", "--set", "horizon=10",
                        "--out", str(tmp_path / "r"), "--quiet")
    assert code == 2
    assert "infeasible for the centralised problem at N = 10" in err
    assert (f"the smallest horizon for which the distributed k = 0 step finds a plan for every agent is "
            f"N = {start['smallest_feasible']} (the centralised problem alone is feasible from "
            f"N = {start['smallest_centrally_feasible']})") in err
    assert f"horizon: auto (N = {design['horizon']} here" in err
    assert not (tmp_path / "r").exists()


# --------------------------------------------------------------------------- checks before the run
def test_a_start_outside_x_is_refused_by_validate_and_design(monkeypatch, capsys, tmp_path):
    path = scenario(tmp_path, xa=(2.0, 3.5))
    for command in ("validate", "design"):
        code, _, err = call(monkeypatch, capsys, command, path)
        assert code == 2
        assert "subsystems[0].x0[1]" in err and "subsystem a" in err and "outside the state set" in err, err


def test_a_start_that_no_horizon_can_save_is_refused(monkeypatch, capsys, tmp_path):
    # moving at 2.9 m/s towards the wall 0.1 m away, with a brake of 1 m/s^2: no plan stays inside
    path = scenario(tmp_path, xa=(4.9, 2.9), xb=(-4.9, -2.9), horizon=40)
    code, _, err = call(monkeypatch, capsys, "simulate", path, "--out", str(tmp_path / "r"), "--quiet")
    assert code == 2
    assert "no horizon up to N = 200 makes it feasible" in err, err


# --------------------------------------------------------------------------- failures
def test_a_far_start_run_anyway_fails_with_state_violated(monkeypatch, capsys, tmp_path):
    path = scenario(tmp_path, xa=(4.9, 2.9), xb=(-4.9, -2.9), horizon=40, steps=40, check=False)
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, path)
    assert code == 3
    assert summary["verdict"] == "failed"
    assert {"state-violated", "infeasible-start"} <= kinds(summary["failures"])
    violated = {f["subsystem"]: f for f in summary["failures"] if f["kind"] == "state-violated"}
    assert set(violated) == {"a", "b"}
    for name, f in violated.items():
        assert f["amount"] == pytest.approx(summary["state_bound_excess"][name]) and f["amount"] > 0
        assert f["steps"]
    first = out.splitlines()[0]
    assert first.startswith("verdict: FAILED (") and "state-violated" in first
    assert "failure state-violated: subsystem a: state outside its bounds by up to" in out
    assert ("failure infeasible-start: no feasible plan at k = 0 for subsystem(s) a, b; no centralised seed: OSQP "
            "reported the centralised QP infeasible; the start was not checked (design.check_start: false)") in out


def test_tiny_inputs_on_the_paper_diverge(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/paper.yaml", "--set",
                                     "subsystems[0].input={lower: [-0.01], upper: [0.01]}", "--set",
                                     "terminal.beta0=auto", "--set", "design.check_start=false")
    assert code == 3
    assert {"diverged", "infeasible-start"} <= kinds(summary["failures"])
    assert "not-converged" not in kinds(summary["warnings"])  # said once, as a failure
    assert "failure diverged: ||x(k)||_inf reached" in out
    assert "note k=0: round 0 infeasible" in out


def test_the_tiny_input_paper_is_refused_before_running(monkeypatch, capsys, tmp_path):
    code, _, err = call(monkeypatch, capsys, "simulate", "scenarios/paper.yaml", "--set",
                        "subsystems[0].input={lower: [-0.01], upper: [0.01]}", "--set", "terminal.beta0=auto",
                        "--out", str(tmp_path / "r"), "--quiet")
    assert code == 2 and "infeasible for the centralised problem at N = 10" in err


def test_a_qp_failing_after_k0_is_an_infeasible_failure(monkeypatch, capsys, tmp_path):
    original = AgentController.solve

    def failing(self, k, *args, **kwargs):
        sol = original(self, k, *args, **kwargs)
        if self.index == 1 and k in (3, 4):
            return type(sol)(QPStatus.INFEASIBLE, np.full_like(sol.z, np.nan), np.full_like(sol.v, np.nan),
                             float("nan"), sol.solve_time, sol.iterations)
        return sol

    monkeypatch.setattr(AgentController, "solve", failing)
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/paper.yaml")
    assert code == 3
    [f] = [f for f in summary["failures"] if f["kind"] == "infeasible"]
    assert f["subsystem"] == "2" and f["steps"] == [3, 4]
    assert "failure infeasible: subsystem 2: QP failed (qp infeasible) at 2 step(s) (k = 3, 4)" in out


# --------------------------------------------------------------------------- warnings
def test_a_short_run_warns_not_converged_but_is_ok(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/paper.yaml", "--steps", "5")
    assert code == 0 and summary["verdict"] == "ok"
    assert kinds(summary["warnings"]) == {"not-converged"}
    assert out.splitlines()[0] == "verdict: ok (1 warning)"


def test_a_jacobi_cap_is_a_warning_on_screen(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/paper.yaml", "--set",
                                     "options.initial_iterations=3")
    assert code == 0
    [w] = [w for w in summary["warnings"] if w["kind"] == "jacobi-cap"]
    assert w["steps"] == [0] and w["amount"] > 1e-9
    assert "warning jacobi-cap" in out


def test_lost_messages_are_a_fallbacks_warning(monkeypatch, capsys, tmp_path):
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path, "scenarios/paper.yaml", "--set",
                                     "faults.loss=0.2", "--set", "options.mode=realtime", "--set",
                                     "options.deadline=0.05", "--set", "seed=3")
    assert summary["fallbacks"] > 0
    [w] = [w for w in summary["warnings"] if w["kind"] == "fallbacks"]
    assert w["amount"] == summary["fallbacks"]
    assert "failures" in summary and not {"infeasible", "infeasible-start"} & kinds(summary["failures"])
    assert code == (0 if summary["verdict"] == "ok" else 3)


# --------------------------------------------------------------------------- judge, unit
def _system(state: LinearSet | None = None) -> CoupledSystem:
    sub = Subsystem("s", np.eye(1), np.eye(1), np.eye(1), np.eye(1), np.array([1.0]), LinearSet.box([-1], [1]), state)
    return CoupledSystem((sub,))


def _arrays(x, u, rounds=None, change=None) -> dict:
    x, u = np.asarray(x, float).reshape(-1, 1), np.asarray(u, float).reshape(-1, 1)
    K = u.shape[0]
    return {"x": x, "u": u, "fallback": np.zeros((K, 1), bool), "rounds": np.asarray(rounds or [1] * K),
            "max_change": np.asarray(change or [0.0] * K, float)}


def test_judge_input_violated_names_the_excess_and_steps():
    v = judge(_system(), _arrays([1, 0.5, 0.2, 0.1], [-1.5, -0.3, 1.2]), [], RunLimits(3))
    [f] = v.failures
    assert f.kind == "input-violated" and f.steps == [0, 2] and f.amount == pytest.approx(0.5)
    assert v.word == "failed"


def test_judge_tolerates_solver_rounding_on_bounds():
    v = judge(_system(LinearSet.box([-1], [1])), _arrays([1 + 5e-7, 0.5, 0.0], [-1 - 5e-7, -0.5]), [],
              RunLimits(2))
    assert v.ok and not v.failures


def test_judge_diverged_and_nonfinite():
    grown = judge(_system(), _arrays([1, 10, 1000], [0, 0]), [], RunLimits(2))
    assert [f.kind for f in grown.failures] == ["diverged"] and grown.failures[0].steps == [2]
    assert 10 < DIVERGENCE_FACTOR < 1000
    nan = judge(_system(), _arrays([1, np.nan, np.nan], [0, 0]), [], RunLimits(2))
    assert nan.failures[0].kind == "diverged" and nan.failures[0].steps == [1, 2]


def test_judge_incomplete_and_refused_inputs():
    v = judge(_system(), _arrays([1, 0.001], [0]), [], RunLimits(5), inputs_refused={"s": 2})
    assert [f.kind for f in v.failures] == ["incomplete"]
    assert [w.kind for w in v.warnings] == ["inputs-refused"] and v.warnings[0].amount == 2


def test_state_bound_excess_per_subsystem_and_polytopes():
    poly = LinearSet.polytope([[1.0]], [0.5])
    assert state_bound_excess(_system(poly), np.array([[0.2], [0.9]])) == {"s": pytest.approx(0.4)}
    assert state_bound_excess(_system(None), np.array([[0.2]])) == {"s": None}
    assert poly.excess(np.array([[0.2]]))[0] == pytest.approx(-0.3)


def test_the_horizon_search_finds_the_smallest_feasible_horizon():
    from dmpc.offline.start import smallest_feasible_horizon

    for smallest in (1, 2, 3, 7, 8, 9, 63, 64, 65, 150, 200):
        tried = []
        found = smallest_feasible_horizon(lambda N, tried=tried, smallest=smallest: tried.append(N) or N >= smallest, 200)
        assert found == smallest and len(tried) <= 2 * 8 + 64
    assert smallest_feasible_horizon(lambda N: False, 200) is None
