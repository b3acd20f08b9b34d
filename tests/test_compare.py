"""``dmpc compare`` and ``dmpc roa``: their files, their tables, reproducibility, bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dmpc.evaluation.compare import steps_to
from dmpc.evaluation.roa import region_of_attraction, roa_markdown, sample_states
from dmpc.methods import METHOD_NAMES
from dmpc.scenario import load_scenario
from tests.helpers.cli import call, one_error_line
from tests.helpers.reference import PAPER

ENTRY_KEYS = {"run_dir", "closed_loop_cost", "J", "S", "steps_to_1e-3", "feasible", "fallbacks", "solve_time_median_s",
              "verdict", "failures"}


# --------------------------------------------------------------------------- compare
def test_compare_writes_run_folders_and_comparison_json(tmp_path, monkeypatch, capsys):
    out = tmp_path / "cmp"
    code, stdout, _ = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(out), "--steps", "6",
                           "--methods", "tv-box", "fixed-box", "centralized", "--quiet")
    assert code == 0
    data = json.loads((out / "comparison.json").read_text())
    assert set(data) == {"scenario", "methods"} and data["scenario"] == "paper"
    assert list(data["methods"]) == ["tv-box", "fixed-box", "centralized"]
    for method, entry in data["methods"].items():
        assert set(entry) == ENTRY_KEYS
        assert entry["run_dir"] == method
        assert (out / method / "summary.json").exists() and (out / method / "trajectory.npz").exists()
        assert len(entry["J"]) == 6 and len(entry["S"]) == 7
        assert entry["feasible"] and entry["fallbacks"] == 0
        assert entry["steps_to_1e-3"] is None  # not within 6 steps
    assert "tv-box / centralized" in stdout and "fixed-box" in stdout


def test_compare_exits_3_naming_the_methods_whose_verdict_failed(tmp_path, monkeypatch, capsys):
    # at N = 3 the paper's start is infeasible for the boxes at k = 0, not for the centralised QP on X^f
    out = tmp_path / "cmp"
    code, stdout, err = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(out), "--steps", "4",
                             "--methods", "tv-box", "centralized", "--set", "horizon=3", "--set",
                             "design.check_start=false", "--quiet")
    assert code == 3
    data = json.loads((out / "comparison.json").read_text())["methods"]
    assert data["tv-box"]["verdict"] == "failed" and data["centralized"]["verdict"] == "ok"
    line = one_error_line(err)
    assert line.startswith("error: verdict failed for tv-box (") and "centralized" not in line
    assert "failed (infeasible-start)" in stdout


def test_compare_written_to_files_has_no_blank_lines(tmp_path, monkeypatch, capsys):
    """Progress bars are for a terminal: in a file they would leave one blank line per method."""
    code, stdout, err = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(tmp_path / "c"), "--steps", "2",
                             "--methods", "tv-box", "fixed-box", "centralized")
    assert code == 0
    assert err == ""
    lines = stdout.splitlines()
    assert lines[0] == "methods on 'paper'" and len(lines) > 6
    assert sum(not line.strip() for line in lines) <= 2  # the table's own top and bottom rule


def test_steps_to_tolerance():
    x = np.array([[1.0, 2.0], [1e-2, 0.0], [5e-4, -9e-4], [0.0, 0.0]])
    assert steps_to(x) == 2
    assert steps_to(x[:2]) is None


@pytest.mark.parametrize("argv, expected", [
    (["--methods", "tv-box", "nonsense"], "--methods: unknown method 'nonsense'"),
    (["--methods", "tv-box", "tv-box"], "listed twice"),
    (["--set", "horizon=0"], "horizon"),
])
def test_compare_bad_input_exits_2_with_one_line(tmp_path, monkeypatch, capsys, argv, expected):
    code, _, err = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(tmp_path / "c"), *argv)
    assert code == 2
    assert expected in one_error_line(err)


def test_compare_refuses_a_used_folder(tmp_path, monkeypatch, capsys):
    out = tmp_path / "c"
    args = ["compare", str(PAPER), "--out", str(out), "--steps", "2", "--methods", "tv-box", "--quiet"]
    assert call(monkeypatch, capsys, *args)[0] == 0
    code, _, err = call(monkeypatch, capsys, *args)
    assert code == 2 and "already holds a comparison" in one_error_line(err)


def test_compare_missing_scenario_exits_2(tmp_path, monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "compare", str(tmp_path / "none.yaml"), "--out", str(tmp_path / "c"))
    assert code == 2
    one_error_line(err)


# --------------------------------------------------------------------------- roa
def test_roa_is_reproducible_from_the_seed():
    scn = load_scenario(PAPER)
    args = dict(horizons=[3], methods=["tv-box", "tv-box-opt", "centralized"], samples=6)
    first = region_of_attraction(scn, seed=4, **args)
    again = region_of_attraction(scn, seed=4, **args)
    assert first == again
    assert roa_markdown(first) == roa_markdown(again)
    assert not np.array_equal(sample_states(8, 6, 2.8, 4), sample_states(8, 6, 2.8, 5))


def test_sample_states_are_uniform_in_the_box_and_seeded():
    X = sample_states(8, 1000, 2.8, 0)
    assert X.shape == (1000, 8) and np.abs(X).max() <= 2.8
    assert np.array_equal(X, sample_states(8, 1000, 2.8, 0))
    assert abs(X.mean()) < 0.1 and X.min() < -2.7 and X.max() > 2.7


def test_roa_fractions_are_consistent():
    data = region_of_attraction(load_scenario(PAPER), [3, 10], ["tv-box", "centralized"], samples=8, seed=0, box=2.0)
    assert data["box"] == 2.0 and data["samples"] == 8 and data["horizons"] == [3, 10]
    for per_N in data["methods"].values():
        for r in per_N.values():
            assert 0 <= r["always_feasible"] <= min(r["converged"], r["feasible_k0"])
            assert r["feasible_k0"] == np.mean(r["feasible_k0_samples"])
    # with the terminal set X^f itself, the centralised QP is feasible from at least as many states
    assert data["methods"]["centralized"]["3"]["feasible_k0"] >= data["methods"]["tv-box"]["3"]["feasible_k0"]


def test_roa_cli_writes_json_plot_and_the_same_table_twice(tmp_path, monkeypatch, capsys):
    tables = []
    for name in ("a", "b"):
        out = tmp_path / name
        code, stdout, _ = call(monkeypatch, capsys, "roa", str(PAPER), "--N", "3", "5", "--samples", "4", "--seed",
                               "2", "--methods", "tv-box", "centralized", "--out", str(out), "--quiet")
        assert code == 0
        assert (out / "roa.json").exists() and (out / "roa.png").stat().st_size > 10_000
        data = json.loads((out / "roa.json").read_text())
        assert data["horizons"] == [3, 5] and list(data["methods"]) == ["tv-box", "centralized"]
        tables.append(stdout.split("results:")[0])
        assert "feasible at k=0" in stdout
    assert tables[0] == tables[1]
    assert json.loads((tmp_path / "a" / "roa.json").read_text()) == json.loads((tmp_path / "b" / "roa.json").read_text())


def test_roa_refuses_a_folder_that_holds_a_table_and_keeps_it(tmp_path, monkeypatch, capsys):
    out = tmp_path / "r"
    out.mkdir()
    (out / "roa.json").write_text('{"kept": true}')
    code, _, err = call(monkeypatch, capsys, "roa", str(PAPER), "--N", "3", "--samples", "2", "--out", str(out),
                        "--quiet")
    assert code == 2 and "already holds a region-of-attraction table (roa.json exists)" in one_error_line(err)
    assert json.loads((out / "roa.json").read_text()) == {"kept": True}


@pytest.mark.parametrize("argv, expected", [
    (["--N", "0"], "--N"),
    (["--N", "3", "3"], "listed twice"),
    (["--N", "abc"], "abc"),
    (["--samples", "0"], "--samples"),
    (["--box", "-1"], "--box"),
    (["--box", "inf"], "--box"),
    (["--seed", "-3"], "--seed"),
    (["--methods", "ellipse"], "unknown method 'ellipse'"),
])
def test_roa_bad_input_exits_2_with_one_line(tmp_path, monkeypatch, capsys, argv, expected):
    code, _, err = call(monkeypatch, capsys, "roa", str(PAPER), "--out", str(tmp_path / "r"), *argv)
    assert code == 2
    assert expected in err and "Traceback" not in err
    if "abc" not in argv:  # click's own usage errors print a usage line too
        one_error_line(err)


# --------------------------------------------------------------------------- --method on simulate and run
def test_simulate_with_a_method_records_it(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    code, _, _ = call(monkeypatch, capsys, "simulate", str(PAPER), "--method", "ellipsoid", "--steps", "3",
                      "--out", str(out), "--quiet")
    assert code == 0
    assert json.loads((out / "summary.json").read_text())["method"] == "ellipsoid"
    assert "method: ellipsoid" in (out / "scenario.yaml").read_text()
    assert np.load(out / "trajectory.npz")["r"].shape == (4, 4)


@pytest.mark.parametrize("argv, expected", [
    (["simulate", str(PAPER), "--method", "boxes"], "--method: unknown method 'boxes'"),
    (["run", str(PAPER), "--method", "centralized", "--delay", "5"], "--delay"),
    (["agent", str(PAPER), "--id", "1", "--set", "options.method=centralized"], "runs no agents"),
    (["plant", str(PAPER), "--out", "x", "--set", "options.method=centralized"], "runs no agents"),
])
def test_method_bad_input_exits_2(monkeypatch, capsys, argv, expected):
    code, _, err = call(monkeypatch, capsys, *argv)
    assert code == 2
    assert expected in one_error_line(err)


def test_run_centralized_runs_in_this_process(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    code, stdout, err = call(monkeypatch, capsys, "run", str(PAPER), "--method", "centralized", "--steps", "3",
                             "--out", str(out), "--quiet")
    assert code == 0 and "no agents" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "centralized" and summary["steps"] == 3 and summary["feasible"]
    assert not (out / "processes.json").exists()


# --------------------------------------------------------------------------- compare with setpoints
SETPOINT = ["--set", 'setpoints=[{at: 0, subsystem: "1", x: [1.0, null]}]']


UNTRACKED = ("fixed-box", "ellipsoid", "ellipsoid-adaptive")
"""The methods that do not track setpoints (they would drive the states to the origin)."""


def test_compare_with_setpoints_runs_the_methods_that_track_them_and_names_the_others(tmp_path, monkeypatch, capsys):
    out = tmp_path / "cmp"
    code, stdout, _ = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(out), "--steps", "30",
                           *SETPOINT, "--quiet")
    assert code == 0
    data = json.loads((out / "comparison.json").read_text())
    assert list(data["methods"]) == ["tv-box", "tv-box-opt", "tv-box-coop", "centralized"]
    assert list(data["skipped"]) == list(UNTRACKED) and "triggers" not in data
    for name in UNTRACKED:
        why = data["skipped"][name]
        assert why.startswith(f"method '{name}' does not track setpoints (methods that do: tv-box, tv-box-opt, "
                              "tv-box-coop, centralized)"), why
        assert f"not run: {name}: {why}" in stdout
        assert not (out / name).exists()
    for name in ("tv-box", "centralized"):  # the centralised baseline tracks the same targets
        entry = data["methods"][name]
        assert set(entry) == ENTRY_KEYS | {"tracking_cost"}
        arrays = np.load(out / name / "trajectory.npz")
        assert arrays["target"][-1][0] == pytest.approx(1.0) and entry["steps_to_1e-3"] is not None  # from the target
        assert entry["verdict"] == "ok" and entry["feasible"] and entry["fallbacks"] == 0
        dx, du = arrays["x"][:30] - arrays["reference"], arrays["u"] - arrays["reference_u"]
        by_hand = sum(dx[k] @ dx[k] + 0.01 * du[k] @ du[k] for k in range(30))  # Q_i = I, R_i = 0.01
        assert entry["tracking_cost"] == pytest.approx(by_hand, rel=1e-12)
    central, box = (data["methods"][m] for m in ("centralized", "tv-box"))
    assert central["closed_loop_cost"] <= box["closed_loop_cost"] * (1 + 1e-6)
    assert central["tracking_cost"] <= box["tracking_cost"] * (1 + 1e-6)
    assert "||x(k) - x_s||_inf" in stdout and "closed-loop cost tv-box / centralized = " in stdout
    assert "tracking / central" in stdout
    ratio = box["tracking_cost"] / central["tracking_cost"]
    assert f"tracking cost tv-box / centralized = {ratio:.4f} (around the references)" in stdout


def test_without_setpoints_or_triggers_nothing_is_skipped():
    from dmpc.evaluation.compare import plan_runs

    runs, skipped = plan_runs(list(METHOD_NAMES), ["always"])
    assert runs == [(m, "always") for m in METHOD_NAMES] and skipped == {}


def test_setpoints_and_triggers_together_skip_each_run_a_method_cannot_make():
    from dmpc.evaluation.compare import plan_runs

    runs, skipped = plan_runs(list(METHOD_NAMES), ["always", "event"], setpoints=True)
    assert runs == [("tv-box", "always"), ("tv-box", "event"), ("tv-box-opt", "always"), ("tv-box-opt", "event"),
                    ("tv-box-coop", "always"), ("centralized", "always")]
    assert set(skipped) == {"tv-box-coop+event", "centralized+event"} | {
        f"{m}{t}" for m in UNTRACKED for t in ("", "+event")}
    assert skipped["ellipsoid+event"].startswith("method 'ellipsoid' does not track setpoints")  # the first reason
    assert skipped["centralized+event"] == ("method 'centralized' does not work with the event trigger (methods that "
                                            "do: tv-box, tv-box-opt)")


def test_compare_refuses_a_method_that_does_not_track_the_scenarios_setpoints(tmp_path, monkeypatch, capsys):
    code, stdout, err = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(tmp_path / "cmp"),
                             "--methods", "tv-box", "ellipsoid", *SETPOINT, "--quiet")
    assert code == 2 and stdout == ""
    assert "--methods: method 'ellipsoid' does not track setpoints (methods that do: " in one_error_line(err)
    assert not (tmp_path / "cmp").exists()


def test_roa_refuses_a_scenario_with_setpoints(tmp_path, monkeypatch, capsys):
    code, _, err = call(monkeypatch, capsys, "roa", str(PAPER), *SETPOINT, "--out", str(tmp_path / "roa"), "--quiet")
    assert code == 2 and "dmpc roa measures where regulation to the origin succeeds" in one_error_line(err)



# --------------------------------------------------------------------------- compare with triggers
TRIGGER_KEYS = {"method", "trigger", "trigger_cost", "solves", "keeps", "plan_messages", "kept_notices", "bytes",
                "solve_reasons", "step_time_median_s"}


def test_compare_runs_each_method_with_each_trigger(tmp_path, monkeypatch, capsys):
    out = tmp_path / "cmp"
    code, stdout, _ = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(out), "--steps", "20",
                           "--methods", "tv-box", "ellipsoid", "centralized", "--triggers", "always", "event", "--quiet")
    assert code == 0
    data = json.loads((out / "comparison.json").read_text())
    assert list(data["methods"]) == ["tv-box", "tv-box+event", "ellipsoid", "centralized"]
    assert data["triggers"] == ["always", "event"]
    assert set(data["skipped"]) == {"ellipsoid+event", "centralized+event"}
    assert data["skipped"]["ellipsoid+event"] == ("method 'ellipsoid' does not work with the event trigger (methods "
                                                  "that do: tv-box, tv-box-opt)")
    for name, entry in data["methods"].items():
        assert set(entry) == ENTRY_KEYS | TRIGGER_KEYS, name
        assert entry["run_dir"] == name and (out / name / "summary.json").exists()
        assert entry["step_time_median_s"] > 0
    always, event = data["methods"]["tv-box"], data["methods"]["tv-box+event"]
    assert (event["method"], event["trigger"], event["trigger_cost"]) == ("tv-box", "event", 1e-3)
    assert (always["trigger"], always["trigger_cost"], always["keeps"], always["kept_notices"]) == ("always", None, 0, 0)
    assert always["solves"] == always["plan_messages"] and event["solves"] == event["plan_messages"]
    assert event["keeps"] == event["kept_notices"] > 0 and event["solves"] < always["solves"]
    assert event["bytes"] < always["bytes"] and sum(event["solve_reasons"].values()) > 0
    assert event["closed_loop_cost"] == pytest.approx(always["closed_loop_cost"], rel=1e-4)
    assert event["solve_time_median_s"] > 0  # the agent-steps that solved, not the kept ones
    central = data["methods"]["centralized"]
    assert central["solves"] is None and central["bytes"] is None
    header = next(line for line in stdout.splitlines() if "verdict" in line and "feasible" in line)
    assert header.split()[-8:] == ["/", "always", "solves", "kept", "plans", "kB", "step", "ms"]
    row = next(line for line in stdout.splitlines() if line.lstrip().startswith("tv-box+event"))
    assert f" {event['solves']} " in row and f" {event['keeps']} " in row
    assert "not run: ellipsoid+event: method 'ellipsoid' does not work with the event trigger" in stdout
    assert (out / "figures" / "fig4_cost.png").exists()


def test_a_scenario_with_the_event_trigger_runs_the_methods_that_support_it(tmp_path, monkeypatch, capsys):
    out = tmp_path / "cmp"
    code, stdout, _ = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(out), "--steps", "20",
                           "--methods", "tv-box", "fixed-box", "--set", "options.trigger=event",
                           "--set", "options.trigger_cost=10", "--quiet")
    assert code == 0
    data = json.loads((out / "comparison.json").read_text())
    assert list(data["methods"]) == ["tv-box+event"] and list(data["skipped"]) == ["fixed-box+event"]
    assert data["triggers"] == ["event"] and data["methods"]["tv-box+event"]["trigger_cost"] == 10


@pytest.mark.parametrize("argv, expected", [
    (["--triggers", "sometimes"], "--triggers: unknown trigger 'sometimes'"),
    (["--triggers", "event", "event"], "--triggers: a trigger is listed twice"),
    (["--methods", "ellipsoid", "centralized", "--triggers", "event"],
     "--triggers: none of the methods ellipsoid, centralized works with the trigger event"),
    (["--triggers", "always", "event", "--set", "options.iterations=2"], "'event' needs one Jacobi round per step"),
])
def test_compare_bad_triggers_exit_2_before_anything_is_written(tmp_path, monkeypatch, capsys, argv, expected):
    code, stdout, err = call(monkeypatch, capsys, "compare", str(PAPER), "--out", str(tmp_path / "c"), *argv)
    assert code == 2 and stdout == ""
    assert expected in one_error_line(err)
    assert not (tmp_path / "c").exists()


def test_the_table_of_a_comparison_with_triggers_has_the_triggers_columns():
    from dmpc.evaluation.compare import comparison_header, comparison_rows

    base = {"closed_loop_cost": 100.0, "solve_time_median_s": 1e-4, "feasible": True, "fallbacks": 0,
            "steps_to_1e-3": 12, "verdict": "ok", "failures": []}
    always = dict(base, method="tv-box", trigger="always", solves=40, keeps=0, plan_messages=40, bytes=20_000,
                  step_time_median_s=2e-3)
    event = dict(always, trigger="event", closed_loop_cost=100.002, solves=10, keeps=30, plan_messages=10,
                 bytes=6_500, step_time_median_s=1.5e-3)
    data = {"methods": {"tv-box": always, "tv-box+event": event}, "triggers": ["always", "event"], "skipped": {}}
    assert comparison_header(data)[-6:] == ["/ always", "solves", "kept", "plans", "kB", "step ms"]
    rows = comparison_rows(data)
    assert rows[0][-6:] == ["-", "40", "0", "40", "20.0", "2.00"]
    assert rows[1][-6:] == ["1.000020", "10", "30", "10", "6.5", "1.50"]
    assert len(comparison_rows({"methods": {"tv-box": base}})[0]) == 8  # without triggers: as before


def test_the_table_of_a_comparison_with_setpoints_has_the_tracking_column():
    from dmpc.evaluation.compare import comparison_header, comparison_legend, comparison_rows

    base = {"closed_loop_cost": 100.0, "solve_time_median_s": 1e-4, "feasible": True, "fallbacks": 0,
            "steps_to_1e-3": 12, "verdict": "ok", "failures": []}
    data = {"methods": {"tv-box": dict(base, closed_loop_cost=90.0, tracking_cost=120.0),
                        "centralized": dict(base, tracking_cost=100.0)}, "skipped": {}}
    header = comparison_header(data)
    assert header[header.index("/ central") + 1] == "tracking / central" and len(header) == 9
    rows = comparison_rows(data)
    assert rows[0][5:7] == ["0.9000", "1.2000"] and rows[1][5:7] == ["1.0000", "1.0000"]
    assert "tracking / central: " in comparison_legend(data)
