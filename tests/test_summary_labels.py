"""What the run summary, the verdict and the figures say is what happened, in the scenario's own terms.

The J(k) row keeps each value under its own step, "every QP feasible" tells failed QPs from
plans that never arrived, a diverged cost is printed in scientific notation, failure messages and
figures use the scenario's names, units and seconds, and a run without steps is not drawn.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import matplotlib
import numpy as np
import pytest

import dmpc
from dmpc.plots import report as figures
from dmpc.records.session import RunRecorder
from dmpc.records.tables import first_costs, number_text, print_summary
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.cli import call, one_error_line

matplotlib.use("Agg")

PAPER = "scenarios/paper.yaml"
ROOMS = "scenarios/rooms.yaml"


def sets(**overrides) -> list[str]:
    return [arg for key, value in overrides.items() for arg in ("--set", f"{key}={value}")]


def simulate(monkeypatch, capsys, scenario: str, out: Path, *argv: str) -> tuple[int, str, dict]:
    code, stdout, err = call(monkeypatch, capsys, "simulate", scenario, "--out", str(out), "--quiet", *argv)
    assert (out / "summary.json").exists(), err
    return code, stdout, json.loads((out / "summary.json").read_text())


def summary_row(stdout: str, label: str) -> str:
    """The value of one row of the printed run summary."""
    row = next(line for line in stdout.splitlines() if line.startswith(f"│ {label} "))
    return row.split("│")[2].strip()


# --------------------------------------------------------------------------- J(0..3)
def test_the_cost_row_keeps_each_value_under_its_own_step(capsys):
    summary = {"verdict": "ok", "failures": [], "warnings": [], "scenario": "s", "steps": 6, "feasible": False,
               "qp_failed": 0, "plans_missing": 3, "fallbacks": 3, "max_abs_u": 1.0,
               "J": [None, float("nan"), 65.664, 62.758, 60.0, 59.0], "closed_loop_cost": 90.98,
               "final_state_norm_inf": 0.5}
    print_summary(summary, "runs/x")
    out = capsys.readouterr().out
    assert summary_row(out, "J(0..3)") == "n/a, n/a, 65.66, 62.76"
    assert first_costs([1.0]) == ("J(0)", "1.00")
    assert first_costs([]) == ("J(k)", "none (no step completed)")


# --------------------------------------------------------------------------- every QP feasible
def test_lost_plans_are_not_called_infeasible_qps(monkeypatch, capsys, tmp_path):
    code, _, summary = simulate(monkeypatch, capsys, PAPER, tmp_path / "r",
                                *sets(**{"faults.loss": 0.2, "options.deadline": 0.05, "seed": 3}))
    assert code == 0
    print_summary(summary, tmp_path / "r")
    out = capsys.readouterr().out
    assert summary["fallbacks"] > 0 and summary["qp_failed"] == 0 and summary["plans_missing"] == summary["fallbacks"]
    assert summary_row(out, "every QP feasible") == (f"no QP failed; {summary['fallbacks']} plans missed or lost "
                                                     "(fallbacks)")


def test_failed_qps_are_counted_as_such(monkeypatch, capsys, tmp_path):
    code, _, summary = simulate(monkeypatch, capsys, PAPER, tmp_path / "r",
                                *sets(horizon=3, **{"design.check_start": "false", "steps": 6}))
    print_summary(summary, tmp_path / "r")
    out = capsys.readouterr().out
    assert code == 3 and summary["qp_failed"] > 0 and summary["plans_missing"] == 0
    assert summary_row(out, "every QP feasible") == f"no: {summary['qp_failed']} QP solves gave no plan"


# --------------------------------------------------------------------------- numbers
def test_a_diverged_cost_is_printed_in_scientific_notation(monkeypatch, capsys, tmp_path):
    code, out, summary = simulate(monkeypatch, capsys, PAPER, tmp_path / "r",
                                  "--set", "subsystems[0].input={lower: [-0.01], upper: [0.01]}",
                                  *sets(**{"terminal.beta0": "auto", "design.check_start": "false"}))
    assert code == 3 and summary["closed_loop_cost"] > 1e10
    print_summary(summary, tmp_path / "r")
    shown = summary_row(capsys.readouterr().out, "closed-loop cost")
    assert re.fullmatch(r"\d\.\d{4}e\+\d\d", shown), shown
    assert float(shown) == pytest.approx(summary["closed_loop_cost"], rel=1e-4)


@pytest.mark.parametrize("value, text", [(93.68384, "93.6838"), (0.0, "0.0000"), (2.5873e17, "2.5873e+17"),
                                         (1.2e-5, "1.2000e-05"), (None, "n/a"), (float("nan"), "n/a"),
                                         (float("inf"), "inf")])
def test_number_text(value, text):
    assert number_text(value) == text


def test_compare_prints_a_diverged_cost_in_scientific_notation():
    from dmpc.evaluation.compare import comparison_rows

    entry = {"closed_loop_cost": 2.5873e17, "solve_time_median_s": 1e-4, "feasible": False, "fallbacks": 3,
             "steps_to_1e-3": None, "verdict": "failed", "failures": ["diverged"]}
    ref = dict(entry, closed_loop_cost=93.7, verdict="ok", failures=[])
    rows = comparison_rows({"methods": {"tv-box": entry, "centralized": ref}})
    assert rows[0][4] == "2.5873e+17" and rows[1][4] == "93.7000"


# --------------------------------------------------------------------------- names and units
def test_failure_messages_use_the_scenarios_names_and_units(monkeypatch, capsys, tmp_path):
    # room 1 starts with its mass 7.9 K warm and a weak heater: its air leaves the comfort band
    code, out, summary = simulate(monkeypatch, capsys, ROOMS, tmp_path / "r",
                                  "--set", "subsystems[0].x0=[2.9, 7.9]",
                                  "--set", "subsystems[0].input={lower: [-0.5], upper: [0.5]}",
                                  *sets(horizon=20, steps=10, **{"design.check_start": "false"}))
    violated = next(f for f in summary["failures"] if f["kind"] == "state-violated")
    assert violated["subsystem"] == "room1"
    assert "(Ta [K])" in violated["message"] and "component" not in violated["message"]


def test_unnamed_states_are_still_called_by_their_component(monkeypatch, capsys, tmp_path):
    code, out, summary = simulate(monkeypatch, capsys, "scenarios/carts.yaml", tmp_path / "r",
                                  "--set", "subsystems[0].x0=[4.9, 3.0]",
                                  *sets(horizon=24, steps=10, **{"design.check_start": "false"}))
    violated = next(f for f in summary["failures"] if f["kind"] == "state-violated")
    assert "(component x1)" in violated["message"]


# --------------------------------------------------------------------------- figures
@pytest.fixture(scope="module")
def rooms_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rooms") / "run"
    dmpc.simulate(dmpc.load_scenario(ROOMS, steps=4), out=out)
    return out


def _labels(fig) -> tuple[set[str], set[str]]:
    axes = [ax for ax in fig.axes if ax.get_visible()]
    return {ax.get_xlabel() for ax in axes} - {""}, {ax.get_ylabel() for ax in axes} - {""}


def test_report_figures_are_labelled_like_result_plot(rooms_run):
    import matplotlib.pyplot as plt

    run = figures.load_run(rooms_run)
    states = figures._signal_figure(plt, [(run, run.method)], "x", "states")
    inputs = figures._signal_figure(plt, [(run, run.method)], "u", "inputs")
    plane = figures._fig1(plt, [figures.PlaneSet(run, run.method)], "sets", [])
    cost = figures._series_figure(plt, [("", run.J, {}, run.method)], "J", "cost", run)
    result = dmpc.load_run(rooms_run).plot()
    mine = {"states": _labels(states), "inputs": _labels(inputs), "cost": _labels(cost)}
    theirs = {name: _labels(fig) for name, fig in result.items()}
    assert mine["states"][0] == theirs["states"][0] == {"t [s]"} == mine["cost"][0] == theirs["cost"][0]
    assert mine["states"][1] == theirs["states"][1] == {"Ta [K]", "Tm [K]"}
    assert mine["inputs"][1] == theirs["inputs"][1] == {"P [kW]"}
    assert _labels(plane) == ({"Ta [K]"}, {"Tm [K]", "t [s] (colour of the terminal sets)"})
    line = states.axes[0].get_lines()[0]
    assert line.get_xdata()[1] == 300.0  # seconds, not steps
    solves = figures._solves(plt, run, "solves")
    assert _labels(solves) == ({"t [s]"}, {"agents", "agent"})
    assert solves.axes[1].images[0].get_extent()[:2] == [0.0, 300.0 * run.u.shape[0]]  # the steps in seconds
    plt.close("all")


def test_report_of_a_run_without_steps_is_an_error(monkeypatch, capsys, tmp_path):
    prepared = prepare(load_scenario(PAPER))
    with RunRecorder(tmp_path / "run", prepared, show_progress=False):
        pass  # stopped before its first step
    code, out, err = call(monkeypatch, capsys, "report", str(tmp_path / "run"))
    assert code == 2 and out == ""
    assert "the run completed no step: there is nothing to draw" in one_error_line(err)
    assert not (tmp_path / "run" / "figures").exists()
    assert np.load(tmp_path / "run" / "trajectory.npz")["u"].shape[0] == 0
