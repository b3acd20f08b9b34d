"""The rooms scenario (five rooms in a row, continuous time): it runs, and the horizon advice on it holds.

The rooms are a case where the smallest horizon that is feasible for the centralised problem is
one step short of what the distributed k = 0 step needs: what the design advises, what a run
at the centrally feasible horizon does, and what its messages say are checked here.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

import dmpc
from tests.helpers.cli import call, one_error_line

ROOMS = "scenarios/rooms.yaml"
LIGHT_MASS_WEIGHT = [f"subsystems[{i}].Q=[[1.0, 0.0], [0.0, 0.1]]" for i in range(5)]
"""A lighter weight on the mass temperatures: the rooms' design then needs N = 8 where N = 7 is
centrally feasible, and the centralised QP finds no plan from x(0) at N = 7."""


def sets(*overrides: str) -> list[str]:
    return [arg for o in overrides for arg in ("--set", o)]


def design_of(monkeypatch, capsys, *overrides: str) -> dict:
    code, out, err = call(monkeypatch, capsys, "design", ROOMS, "--json", *sets(*overrides))
    assert code == 0, err
    return json.loads(out)


def simulate(monkeypatch, capsys, out: Path, *overrides: str) -> tuple[int, str, str, dict]:
    code, stdout, stderr = call(monkeypatch, capsys, "simulate", ROOMS, *sets(*overrides), "--out", str(out),
                                "--quiet")
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    return code, stdout, stderr, summary


def test_the_rooms_run_ok_in_process_with_names_units_and_seconds():
    result = dmpc.simulate(dmpc.load_scenario(ROOMS, setpoints=[], steps=144))  # regulation to 21 degC
    assert result.verdict == "ok", result.summary["failures"]
    assert result.summary["warnings"] == []  # the mass too is back within 1 % of the start's size
    assert result.states["room1"][0].name == "Ta" and result.states["room1"][0].unit == "K"
    assert len(result.t) == 145 and result.t[1] == 300.0  # dt = 300 s, 12 h
    x = np.concatenate([result.x[f"room{i}"] for i in range(1, 6)], axis=1)
    u = np.concatenate([result.u[f"room{i}"] for i in range(1, 6)], axis=1)
    assert np.all(np.abs(x[:, 0::2]) <= 3 + 1e-6) and np.all(np.abs(u) <= 2 + 1e-6)  # comfort band, 0-4 kW
    assert np.abs(u).max() > 1.9  # the heaters work at their limits at first


def test_the_rooms_follow_their_day_of_setpoints():
    """The shipped schedule (22:00 to 22:00): every room within 0.3 K of its setpoint when the next
    one takes over and within 0.01 K at the end, the comfort band and the heaters' range held
    throughout, every request reachable and every target reached by the applied one (the reference
    governor) an hour before the next change, and no warning."""
    result = dmpc.simulate(ROOMS)
    summary = result.summary
    assert result.verdict == "ok" and summary["fallbacks"] == 0 and summary["feasible"], summary["failures"]
    assert summary["warnings"] == []
    names = [f"room{i}" for i in range(1, 6)]
    x = np.concatenate([result.x[name] for name in names], axis=1)
    u = np.concatenate([result.u[name] for name in names], axis=1)
    assert np.all(np.abs(x[:, 0::2]) <= 3 + 1e-6) and np.all(np.abs(u) <= 2 + 1e-6)
    for name in names:
        asked, target = result.setpoint[name][:, 0], result.target[name]
        assert np.all(np.isfinite(asked))
        np.testing.assert_allclose(result.reference[name][:, 0], asked, atol=1e-6)  # every request reachable
        np.testing.assert_allclose(target[:, 1], target[:, 0], atol=1e-9)  # steady: the mass at the air's
        changes = [k for k in range(1, len(asked)) if asked[k] != asked[k - 1]] + [len(asked)]
        for k in changes:  # x(k): the state the next setpoint (or the end) finds
            assert abs(result.x[name][k, 0] - asked[k - 1]) <= (0.01 if k == len(asked) else 0.3), (name, k)
            np.testing.assert_allclose(target[k - 12:k, 0], asked[k - 1], atol=1e-6)  # applied an hour before
    assert [(c["subsystem"], c["asked"]) for c in summary["tracking"]["components"]] == [
        ("room1", -1.0), ("room2", -1.0), ("room3", 0.0), ("room4", 0.0), ("room5", -0.5)]


def test_the_rooms_design_needs_more_than_the_centrally_feasible_horizon(monkeypatch, capsys):
    start = design_of(monkeypatch, capsys)["start"]
    assert start["smallest_feasible"] > start["smallest_centrally_feasible"]


def test_a_short_horizon_is_refused_with_a_horizon_that_then_runs_ok(monkeypatch, capsys, tmp_path):
    code, _, err = call(monkeypatch, capsys, "simulate", ROOMS, "--set", "horizon=2", "--out", str(tmp_path / "r"),
                        "--quiet")
    assert code == 2
    line = one_error_line(err)
    advised = int(re.search(r"finds a plan for every agent is N = (\d+)", line).group(1))
    start = design_of(monkeypatch, capsys)["start"]
    assert advised == start["smallest_feasible"]  # what horizon: auto computes, not the centrally feasible one
    assert f"set horizon: {advised} or larger" in line
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path / "advised", f"horizon={advised}")
    assert code == 0 and summary["verdict"] == "ok", out
    assert summary["horizon"] == advised


def test_a_seeded_start_that_an_agent_keeps_does_not_stall_the_run(monkeypatch, capsys, tmp_path):
    """At the centrally feasible horizon room5's QP stays infeasible after the centralised seed: the
    seed is its plan for the step, and every release that refers to it must carry it."""
    start = design_of(monkeypatch, capsys)["start"]
    N = start["smallest_centrally_feasible"]
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path / "r", f"horizon={N}", "steps=3")
    assert any("started from the centralised QP's plan" in note for note in summary["notes"]), summary["notes"]
    assert summary["steps"] == 3, summary["failures"]
    assert code == 0 and summary["verdict"] == "ok", out


def test_a_failed_seed_says_what_the_solver_and_the_start_check_found(monkeypatch, capsys, tmp_path):
    design = design_of(monkeypatch, capsys, *LIGHT_MASS_WEIGHT)
    N = design["start"]["smallest_centrally_feasible"]
    assert design["start"]["smallest_feasible"] == N + 1
    code, out, _, summary = simulate(monkeypatch, capsys, tmp_path / "r", *LIGHT_MASS_WEIGHT, f"horizon={N}",
                                     "steps=2")
    assert code == 3
    assert json.loads((tmp_path / "r" / "design.json").read_text())["start"]["centrally_feasible"] is True
    start_failure = next(f for f in summary["failures"] if f["kind"] == "infeasible-start")
    message = start_failure["message"]
    assert "infeasible too" not in message and "infeasible too" not in out
    assert "no centralised seed: OSQP reported the centralised QP infeasible" in message
    assert f"although the start check (an LP) found x(0) feasible for the centralised problem at N = {N}" in message
    assert "horizon: auto" in message


def test_check_start_false_with_an_auto_horizon_says_to_set_a_number(monkeypatch, capsys, tmp_path):
    far = ["subsystems[0].x0=[2.9, 7.9]", "subsystems[1].x0=[2.9, 7.9]"]  # mass far too warm to cool in time
    code, _, err = call(monkeypatch, capsys, "simulate", ROOMS, *sets(*far, "design.check_start=false"),
                        "--out", str(tmp_path / "r"), "--quiet")
    assert code == 2
    line = one_error_line(err)
    assert line.startswith("error: horizon: auto:")
    assert "design.check_start: false does not apply to horizon: auto" in line
    assert "set a number (horizon: N) to run anyway" in line
    code, _, err = call(monkeypatch, capsys, "simulate", ROOMS, *sets(*far), "--out", str(tmp_path / "r"), "--quiet")
    assert code == 2 and "design.check_start" not in err  # only said where it was set
